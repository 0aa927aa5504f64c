"""Run the benchmark parts and write results/<name>.json (machine info included, figures measured in this run); a
--quick smoke run writes under <output>/quick/ so it never replaces the full-size figures."""
from __future__ import annotations

import argparse
import importlib
import json
import os
import platform
import sys
import time
from pathlib import Path

from mm_bringup.bench import PARTS, write_json


def machine_info() -> dict:
    return {'cpu_count': os.cpu_count(), 'python': platform.python_version(), 'platform': platform.platform(),
            'rmw': os.environ.get('RMW_IMPLEMENTATION', 'rmw_fastrtps_cpp (default)')}


def output_dir(output: str, quick: bool) -> Path:
    """Where a run's JSON goes: a smoke run's smaller sizes must not pass for the full benchmark's figures."""
    return Path(output) / 'quick' if quick else Path(output)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument('--output', default='results')
    parser.add_argument('--only', nargs='*', default=None, help=f'parts to run (default: all of {PARTS})')
    parser.add_argument('--quick', action='store_true', help='smaller sizes for a smoke run (written to <output>/quick)')
    args = parser.parse_args(argv)
    out = output_dir(args.output, args.quick)
    out.mkdir(parents=True, exist_ok=True)
    failed = []
    for name in args.only or PARTS:
        module = importlib.import_module(f'mm_bringup.bench.{name}')
        print(f'[bench] {name} ...', flush=True)
        start = time.monotonic()
        try:
            result = module.run(out, args.quick)
        except Exception as exc:  # report and continue with the other parts; exit non-zero at the end
            print(f'[bench] {name} failed: {exc!r}', file=sys.stderr, flush=True)
            failed.append(name)
            continue
        result['machine'] = machine_info()
        result['bench_seconds'] = round(time.monotonic() - start, 1)
        result['quick'] = args.quick
        write_json(out / f'{module.NAME}.json', result)
        print(f'[bench] {name}: wrote {out / (module.NAME + ".json")}', flush=True)
        print(json.dumps({k: v for k, v in result.items() if not isinstance(v, (dict, list))}, indent=1), flush=True)
    return 1 if failed else 0


if __name__ == '__main__':
    sys.exit(main())
