"""`./mm bag info|play|record`: the venv stand-in for `ros2 bag` on mm's rosbag2 MCAP bags.

    ./mm bag info results/demo_bag
    ./mm bag play results/demo_bag [--rate 2.0] [--clock] [--topics /a /b]
    ./mm bag record -o results/my_bag [-a | /topic ...] [--exclude REGEX] [--compression zstd]
"""
from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path
from typing import List, Optional

from mm_common.rosbag import BagError, read_metadata


def _human_size(n: float) -> str:
    for unit in ('B', 'KiB', 'MiB', 'GiB'):
        if n < 1024 or unit == 'GiB':
            return f'{n:.1f} {unit}'
        n /= 1024
    return f'{n:.1f} GiB'


def format_info(directory: os.PathLike) -> str:
    """A summary in the layout of `ros2 bag info`."""
    directory = Path(directory)
    info = read_metadata(directory)
    files = info.get('relative_file_paths', [])
    size = sum((directory / f).stat().st_size for f in files if (directory / f).exists())
    start = info['starting_time']['nanoseconds_since_epoch']
    duration = info['duration']['nanoseconds']
    lines = [
        f"Files:             {files[0] if files else ''}",
        *[f'                   {f}' for f in files[1:]],
        f'Bag size:          {_human_size(size)}',
        f"Storage id:        {info['storage_identifier']}",
        f'ROS Distro:        {info.get("ros_distro", "")}',
        f'Duration:          {duration / 1e9:.3f}s',
        f'Start:             {start / 1e9:.9f}',
        f'End:               {(start + duration) / 1e9:.9f}',
        f"Messages:          {info['message_count']}",
    ]
    topics = info.get('topics_with_message_count', [])
    for i, t in enumerate(topics):
        meta = t['topic_metadata']
        prefix = 'Topic information: ' if i == 0 else '                   '
        lines.append(f"{prefix}Topic: {meta['name']} | Type: {meta['type']} | Count: {t['message_count']} | "
                     f"Serialization Format: {meta['serialization_format']}")
    if not topics:
        lines.append('Topic information: ')
    return '\n'.join(lines)


def _mm_run(package: str, executable: str, ros_args: List[str]) -> int:
    from mm_bringup.process_graph import executable_path
    os.execv(str(executable_path(package, executable)), [executable, '--ros-args', *ros_args])
    return 0  # not reached


def main(argv: Optional[List[str]] = None) -> int:
    parser = argparse.ArgumentParser(prog='mm bag', description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = parser.add_subparsers(dest='command', required=True)
    p_info = sub.add_parser('info', help='summarise a bag directory')
    p_info.add_argument('bag')
    p_play = sub.add_parser('play', help='replay a bag')
    p_play.add_argument('bag')
    p_play.add_argument('--rate', type=float, default=1.0)
    p_play.add_argument('--clock', action='store_true', help='publish /clock from the recorded times')
    p_play.add_argument('--topics', nargs='*', default=[])
    p_rec = sub.add_parser('record', help='record topics into a new bag')
    p_rec.add_argument('-o', '--output', default='')
    p_rec.add_argument('-a', '--all', action='store_true', help='record all topics (the default)')
    p_rec.add_argument('topics', nargs='*', help='topic names or regexes')
    p_rec.add_argument('--exclude', nargs='*', default=['/rosout', '/parameter_events'])
    p_rec.add_argument('--compression', choices=['none', 'zstd', 'lz4'], default='none')
    p_rec.add_argument('--max-bag-size', type=int, default=0)
    p_rec.add_argument('--overwrite', action='store_true')
    args = parser.parse_args(argv)

    def literal(values: List[str]) -> str:
        return '[' + ','.join(f"'{v}'" for v in values) + ']' if values else "['']"

    try:
        if args.command == 'info':
            print(format_info(args.bag))
            return 0
        if args.command == 'play':
            read_metadata(args.bag)  # fail fast with a clear message
            return _mm_run('mm_bringup', 'player', [
                '-p', f'bag:={args.bag}', '-p', f'rate:={args.rate}', '-p',
                f"publish_clock:={'true' if args.clock else 'false'}", '-p', f'topics:={literal(args.topics)}'])
        topics = [] if args.all else args.topics
        return _mm_run('mm_bringup', 'recorder', [
            '-p', f'output:={args.output}', '-p', f'topics:={literal(topics)}',
            '-p', f'exclude:={literal(args.exclude)}', '-p', f'compression:={args.compression}',
            '-p', f'max_bag_size:={args.max_bag_size}',
            '-p', f"overwrite:={'true' if args.overwrite else 'false'}"])
    except BagError as exc:
        print(f'mm bag: {exc}', file=sys.stderr)
        return 1


if __name__ == '__main__':
    sys.exit(main())
