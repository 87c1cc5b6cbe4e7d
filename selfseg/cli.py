"""The core's command, ``import_videos`` (:mod:`selfseg.importers`): a parser and a thin ``main``."""
from __future__ import annotations

import argparse
import re
import sys
from pathlib import Path

from selfseg.dataset import DatasetError
from selfseg.fileio import FileFormatError
from selfseg.importers import FORMATS, TUM_CAMERAS, run


def _parse_resolution(text: str) -> tuple[int, int]:
    m = re.fullmatch(r"(\d+)x(\d+)", text)
    if not m or int(m[1]) < 1 or int(m[2]) < 1:
        raise argparse.ArgumentTypeError(f"--resolution must look like 320x240, got {text!r}")
    return int(m[1]), int(m[2])


def import_videos_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="import_videos", description="Convert recorded RGB-D videos (YCB-Video, TUM "
                                "RGB-D or a plain folder) into a selfseg dataset, with or without labels.")
    p.add_argument("--format", required=True, choices=FORMATS)
    p.add_argument("sources", nargs="+", type=Path, metavar="SRC", help="a video folder or a folder of them")
    p.add_argument("--out", required=True, type=Path, help="dataset folder to write")
    p.add_argument("--name", help="dataset name (default: the --out folder name)")
    p.add_argument("--frame-step", type=int, default=1, help="keep every N-th frame (default 1)")
    p.add_argument("--resolution", type=_parse_resolution, help="resize every frame to WxH (intrinsics scaled)")
    p.add_argument("--intrinsics", type=Path, help="file with 'fx fy cx cy' or a 3×3 matrix (overrides the source's)")
    p.add_argument("--camera", choices=sorted(TUM_CAMERAS), help="TUM camera name for its published intrinsics")
    p.add_argument("--depth-scale", type=float, default=1.0, help="folder format: millimetres per depth unit (default 1)")
    p.add_argument("--max-dt-s", type=float, default=0.02, help="TUM: max colour–depth time difference (default 0.02 s)")
    p.add_argument("--quiet", action="store_true", help="no progress bars")
    return p


def main(argv: list[str] | None = None) -> int:
    args = import_videos_parser().parse_args(argv)
    try:
        return run(args)
    except (DatasetError, FileFormatError, FileExistsError) as e:
        print(f"import_videos: error: {e}", file=sys.stderr)
    return 2


if __name__ == "__main__":
    sys.exit(main())
