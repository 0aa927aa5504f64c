"""`./mm bag info|play|record|reindex`: the venv stand-in for `ros2 bag` on mm's rosbag2 MCAP bags.

    ./mm bag info results/demo_bag        # counts read from the .mcap files, not just metadata.yaml
    ./mm bag play results/demo_bag [--rate 2.0] [--clock] [--topics /a /b]
    ./mm bag record -o results/my_bag [-a | /topic ...] [--exclude REGEX] [--compression zstd]
    ./mm bag reindex results/my_bag       # complete a crashed recording: indexed .mcap files + metadata.yaml

Errors are one line on stderr and exit status 1.
"""
from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path
from typing import Dict, List, Optional

from mm_common.rosbag import BagError, bag_file_paths, read_metadata, reindex, summarize_file


def _human_size(n: float) -> str:
    for unit in ('B', 'KiB', 'MiB', 'GiB'):
        if n < 1024 or unit == 'GiB':
            return f'{n:.1f} {unit}'
        n /= 1024
    return f'{n:.1f} GiB'


def topic_counts(directory: os.PathLike) -> Dict[str, int]:
    """Messages per topic the bag's .mcap files hold (as format_info counts them)."""
    directory = Path(directory)
    counts: Dict[str, int] = {}
    for path in bag_file_paths(directory, read_metadata(directory)):
        for topic, n in summarize_file(path).counts.items():
            counts[topic] = counts.get(topic, 0) + n
    return counts


def format_info(directory: os.PathLike, prog: str = 'mm bag') -> str:
    """A summary in the layout of `ros2 bag info`, with the message counts the .mcap files really hold (from each
    file's MCAP summary, or by reading the file through when it has none, which a note says). BagError for a
    missing, empty or damaged file."""
    directory = Path(directory)
    info = read_metadata(directory)
    files = info.get('relative_file_paths', [])
    counts: Dict[str, int] = {}
    types: Dict[str, str] = {}
    starts, ends, notes = [], [], []
    for path in bag_file_paths(directory, info):
        summary = summarize_file(path)
        if summary.error:
            hint = f'; `{prog} reindex {directory}` recovers what is readable' if path.is_file() else ''
            raise BagError(f'{path}: {summary.error}{hint}')
        if summary.scanned:
            notes.append(f'Note: {path.name} has no MCAP summary (not closed cleanly); counted by reading it through')
        for topic, n in summary.counts.items():
            counts[topic] = counts.get(topic, 0) + n
            types.setdefault(topic, summary.types.get(topic, ''))
        starts += [summary.start_ns] if summary.start_ns is not None else []
        ends += [summary.end_ns] if summary.end_ns is not None else []
    size = sum((directory / f).stat().st_size for f in files)
    start = min(starts) if starts else 0
    duration = max(ends) - start if ends else 0
    total = sum(counts.values())
    if total != info.get('message_count', 0):
        notes.append(f"Note: metadata.yaml lists {info.get('message_count', 0)} messages, the files hold {total}; "
                     f'`{prog} reindex {directory}` rewrites it')
    lines = [
        f"Files:             {files[0] if files else ''}",
        *[f'                   {f}' for f in files[1:]],
        f'Bag size:          {_human_size(size)}',
        f"Storage id:        {info['storage_identifier']}",
        f'ROS Distro:        {info.get("ros_distro", "")}',
        f'Duration:          {duration / 1e9:.3f}s',
        f'Start:             {start / 1e9:.9f}',
        f'End:               {(start + duration) / 1e9:.9f}',
        f'Messages:          {total}',
    ]
    listed = {t['topic_metadata']['name']: t['topic_metadata'] for t in info.get('topics_with_message_count', [])}
    names = list(listed) + [t for t in counts if t not in listed]
    for i, name in enumerate(names):
        meta = listed.get(name, {})
        prefix = 'Topic information: ' if i == 0 else '                   '
        lines.append(f"{prefix}Topic: {name} | Type: {meta.get('type') or types.get(name, '')} | "
                     f"Count: {counts.get(name, 0)} | "
                     f"Serialization Format: {meta.get('serialization_format', 'cdr')}")
    if not names:
        lines.append('Topic information: ')
    return '\n'.join(lines + notes)


def reindex_bag(directory: os.PathLike) -> str:
    """`bag reindex`: rebuild a crashed recording; the report says what each file held and what was dropped."""
    _, report = reindex(directory)
    return '\n'.join(report)


def _mm_run(package: str, executable: str, ros_args: List[str]) -> int:
    from mm_bringup.process_graph import executable_path
    os.execv(str(executable_path(package, executable)), [executable, '--ros-args', *ros_args])
    return 0  # not reached


def main(argv: Optional[List[str]] = None, prog: str = 'mm bag') -> int:
    parser = argparse.ArgumentParser(prog=prog, description=__doc__,
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
    p_rec.add_argument('--flush-period', type=float, default=0.5,
                       help='seconds after which a chunk is written even if not full (the most a kill -9 loses)')
    p_rec.add_argument('--overwrite', action='store_true')
    p_reindex = sub.add_parser('reindex', help='rebuild the index and metadata.yaml of a crashed recording')
    p_reindex.add_argument('bag')
    args = parser.parse_args(argv)

    def literal(values: List[str]) -> str:
        return '[' + ','.join(f"'{v}'" for v in values) + ']' if values else "['']"

    try:
        if args.command == 'info':
            print(format_info(args.bag, prog))
            return 0
        if args.command == 'reindex':
            print(reindex_bag(args.bag))
            return 0
        if args.command == 'play':
            format_info(args.bag, prog)  # fail fast with one clear line on a missing, empty or damaged file
            return _mm_run('mm_bringup', 'player', [
                '-p', f'bag:={args.bag}', '-p', f'rate:={args.rate}', '-p',
                f"publish_clock:={'true' if args.clock else 'false'}", '-p', f'topics:={literal(args.topics)}'])
        topics = [] if args.all else args.topics
        return _mm_run('mm_bringup', 'recorder', [
            '-p', f'output:={args.output}', '-p', f'topics:={literal(topics)}',
            '-p', f'exclude:={literal(args.exclude)}', '-p', f'compression:={args.compression}',
            '-p', f'max_bag_size:={args.max_bag_size}', '-p', f'flush_period:={args.flush_period}',
            '-p', f"overwrite:={'true' if args.overwrite else 'false'}"])
    except BagError as exc:
        print(f'{prog}: {exc}', file=sys.stderr)
        return 1
    except BrokenPipeError:      # output piped into `head`: not an error; keep Python from complaining at exit
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 0


if __name__ == '__main__':
    sys.exit(main())
