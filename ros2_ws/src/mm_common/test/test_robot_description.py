"""The joint box read from a URDF: what a chain writes is read back exactly; hostile or incomplete descriptions are
refused with the reason."""
import numpy as np
import pytest

from mm_common.robot_description import MAX_DESCRIPTION_CHARS, joint_box, joint_limits_from_urdf, planar_chain_urdf


def test_a_written_chain_reads_back_with_its_movable_joints_in_order():
    text = planar_chain_urdf('arm', [('roll', -3.2, -0.8, 0.11), ('pitch', 0.0, 2.2, 0.09)], 4.0, unit_note='px')
    names, limits = joint_limits_from_urdf(text)
    assert names == ['roll', 'pitch']                    # the fixed tool joint is not movable
    np.testing.assert_array_equal(limits, [[-3.2, -0.8], [0.0, 2.2]])
    np.testing.assert_array_equal(joint_box(text, 2), limits)
    with pytest.raises(ValueError, match='2 movable joint'):
        joint_box(text, 3)


@pytest.mark.parametrize('text, reason', [
    ('', 'empty'),
    ('<robot>', 'well-formed'),
    ('<model/>', 'root element'),
    ('<!DOCTYPE r [<!ENTITY x "y">]><robot/>', 'DTD'),
    ('<robot><joint name="a" type="revolute"/></robot>', 'no numeric'),
    ('<robot><joint name="a" type="revolute"><limit lower="x" upper="1"/></joint></robot>', 'no numeric'),
    ('<robot><joint name="a" type="revolute"><limit lower="1" upper="1"/></joint></robot>', 'lower < upper'),
    ('<robot><joint name="a" type="prismatic"><limit lower="0" upper="inf"/></joint></robot>', 'lower < upper'),
    ('<robot>' + ' ' * MAX_DESCRIPTION_CHARS + '</robot>', 'characters'),
])
def test_bad_descriptions_are_refused_with_the_reason(text, reason):
    with pytest.raises(ValueError, match=reason):
        joint_limits_from_urdf(text)
