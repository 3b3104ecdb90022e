"""``flyscan parts DIR``: example parts to scan, plan and serve, written as CAD files with their
units (``simulator.procedural.write_example_parts``)."""
from __future__ import annotations

from pathlib import Path

from flyscan.common import check_out_dir

__all__ = ["add_parser", "run"]


def add_parser(command) -> None:
    parts = command("parts", help="write example parts (binary STL, with a manifest.json of "
                                  "their units) into a folder")
    parts.add_argument("folder", type=Path, help="where to write them (made if missing)")


def run(args) -> int:
    from simulator.procedural import write_example_parts

    check_out_dir(args.folder)
    manifest = write_example_parts(args.folder)
    for name, entry in manifest.items():
        print(f"{args.folder / name}: {entry['units']} ({entry['source']})")
    print(f"{args.folder / 'manifest.json'}: their units")
    return 0
