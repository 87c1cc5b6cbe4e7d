"""What the config-variant benches share (``bench_supervised_levers.py``, ``bench_matching_levers.py``):
variant parsing, running one variant's command, and keeping earlier rows in the JSON."""
from __future__ import annotations

import subprocess
import sys
import time
from pathlib import Path
from typing import Callable

from selfseg.fileio import read_json, write_json


def parse_variant(text: str) -> tuple[str, list[str]]:
    """"NAME:a=1,b.c=[2,3]" → ("NAME", ["a=1", "b.c=[2,3]"]): commas inside brackets stay in their value."""
    name, _, rest = text.partition(":")
    if not name or any(c in name for c in "/@ "):
        raise ValueError(f"variant {text!r}: needs a NAME (no '/', '@' or space) before ':'")
    items, depth, cur = [], 0, ""
    for c in rest:
        depth += (c in "[{") - (c in "]}")
        if c == "," and depth == 0:
            items.append(cur)
            cur = ""
        else:
            cur += c
    items.append(cur)
    sets = [s.strip() for s in items if s.strip()]
    bad = [s for s in sets if "=" not in s]
    if bad:
        raise ValueError(f"variant {text!r}: {bad} are not key=value")
    return name, sets


def run_variant_command(bench: str, name: str, cmd: list[str], config: str, sets: list[str]) -> float:
    """Run ``cmd`` with ``--config config`` (if given) and a ``--set`` per item of ``sets``, printed first;
    returns its wall time (s). A failed command ends the bench with one line."""
    cmd = [*cmd, *(["--config", config] if config else []), *[a for s in sets for a in ("--set", s)]]
    print(f"[{name}] {' '.join(cmd)}", flush=True)
    t0 = time.perf_counter()
    rc = subprocess.call(cmd)
    if rc != 0:
        raise SystemExit(f"{bench}: variant {name}: {Path(cmd[0]).name} exited with {rc}")
    return time.perf_counter() - t0


def save_rows(path: str | Path, rows: list[dict], ident: Callable[[dict], tuple], what: str) -> None:
    """Write ``rows`` to the JSON at ``path`` after the rows it already holds, minus those with the same ``ident``."""
    path = Path(path)
    old = read_json(path)["rows"] if path.is_file() else []
    new_ids = {ident(r) for r in rows}
    write_json(path, {"what": what, "rows": [r for r in old if ident(r) not in new_ids] + rows})


def parse_inputs(bench: str, variants: list[str], data: str) -> list[tuple[str, list[str]]] | None:
    """The parsed ``--variant`` texts, or None after one line on stderr when one is malformed or ``data`` is
    not a dataset folder (the bench then exits 2)."""
    if not (Path(data) / "dataset_info.json").is_file():
        print(f"{bench}: {data}: not a dataset (no dataset_info.json)", file=sys.stderr)
        return None
    try:
        return [parse_variant(v) for v in variants]
    except ValueError as e:
        print(f"{bench}: {e}", file=sys.stderr)
        return None
