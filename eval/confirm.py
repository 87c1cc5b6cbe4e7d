"""The confirmation protocol: freeze the configs in a commit, run fresh seeds once, pool them, test the claims.

    python -m selfseg.eval.confirm freeze --preset calibrated        # writes leaderboards/calibrated-freeze.json
    python -m selfseg.eval.confirm seeds --preset calibrated         # the fresh seeds, one per line
    python -m selfseg.eval.confirm check --preset calibrated         # may this checkout run them? (exit 2: no)
    python -m selfseg.eval.confirm board --preset calibrated --runs runs/confirm \\
        --dev "seed 0=leaderboards/results/calibrated" [--noisy-runs runs/confirm-noisy]
                                                                     # the section of leaderboards/calibrated.md
    python -m selfseg.eval.confirm compare --results RESULTS --b ours-v2 --b depth-clustering
                                                                     # one seed's paired claims, with verdicts
    python -m selfseg.eval.confirm compare --results NEW --against OLD  # every run of both folders (the same data),
                                                                     # NEW − OLD: did a code change move a row?
    python -m selfseg.eval.confirm archive --preset calibrated --runs runs/confirm [--noisy]
                                                                     # the seeds' finished fold records, into
                                                                     # leaderboards/results/ (to commit)
    python -m selfseg.eval.confirm restore --preset calibrated --runs runs/confirm [--noisy]
                                                                     # put them back on another machine

A preset may be frozen again (``--freeze calibrated-2`` with each command): a change after a freeze is a new
freeze on new seeds, reported beside the first, never instead of it.

**Freeze.** ``freeze`` records the clean HEAD as the freeze commit (its code and every ``configs/`` file's
hash) in ``leaderboards/<preset>-freeze.json``, to be committed at once. The fresh seeds are derived from the
freeze commit's hash (:func:`fresh_seeds`), so nobody can have seen their data before the freeze existed, and
no seed can be picked because it wins; a change to code or configs after the freeze is a new freeze, hence new
seeds (never a development seed nor an earlier freeze's seed of the preset). Each freeze has a name (the preset's
own for the first; ``<preset>-2`` and so on after it), its record ``leaderboards/<name>-freeze.json`` and its own
section of the preset's leaderboard. ``check`` refuses a checkout whose code or configs differ from the freeze commit's (only
``leaderboards/``, ``docs/`` and ``README.md`` may move on), and ``board`` refuses any result record that
ran from such a commit or from a dirty tree.

**Budgets.** A fold whose method passed a compute budget its frozen config declares (``ours``'s matching CPU) has a
failure record instead of scores (:func:`selfseg.eval.protocol.record_failure`) and is never rerun. The board shows
the run as failed on that seed, pools it over the other seeds, and tests a claim on the seeds where both sides ran
every fold: with fewer than :data:`MIN_CLAIM_SEEDS` the claim is "not tested". A Table II row may fail the same way.

**Board.** Per-seed columns (development seeds marked, never pooled), the fresh seeds pooled over every test
frame, and paired differences ``ours`` − each baseline and ablation (V2's, where ``ours`` did not run:
:data:`CLAIMANTS`) with bootstrap 95 % CIs over the pooled test videos (:mod:`selfseg.eval.pooled`); a claim
holds only when its CI excludes 0. Table II per seed too.
The section sits between its own markers in ``leaderboards/<preset>.md``, so the leaderboard builder
(:mod:`selfseg.eval.leaderboard`) leaves it alone.

**Archive.** A seed takes hours and a machine may not outlive a session. ``archive`` copies every finished fold
record of the seeds' runs (``scores/``, ``failed/``, ``rejected/`` and ``timings.tsv``; never predictions or caches)
into ``leaderboards/results/<name>-confirm/`` (``-noisy-confirm`` for ``--noisy``) with a README naming the runs
and their fold counts only, so archiving reads no score. ``restore`` puts them back into a runs folder, where
``KEEP_EARLIER=1 scripts/confirm.sh`` from a clean clone of the freeze keeps them and runs the rest; a kept fold
counts only if the regenerated data has the content hash its record names.

**Noise.** ``board --noisy-runs DIR`` adds the same fresh seeds of the preset's noisy variant (``<preset>-noisy``:
the same scenes with the depth-noise model on; ``DIR/seed-<S>/results``, run from the freeze with its configs,
so nothing is tuned on noise): each method's drop exact − noisy paired per test video, ``ours``'s claims under
noise, and Table II exact → noisy per seed.
"""
from __future__ import annotations

import argparse
import hashlib
import re
import subprocess
import sys
from datetime import datetime, timezone
from pathlib import Path

from selfseg.eval.aggregate import fmt
from selfseg.eval.layout import FAILED_DIR, REJECTED_DIR, SCORES_DIR
from selfseg.eval.leaderboard import load_failures, load_results, replace_generated
from selfseg.eval.pooled import Seed, frame_mean, paired, pooled_videos, score
from selfseg.eval.provenance import cpu_flags, cpu_model, run_key
from selfseg.fileio import FileFormatError, atomic_write_bytes, atomic_write_text, read_json, write_json

ROOT = Path(__file__).resolve().parents[1]
FREEZE_JSON = "leaderboards/{name}-freeze.json"  # a freeze's record, committed right after the freeze commit
SEED_RUN_DIR = "seed-{seed}"  # one fresh seed's run folder (scripts/benchmark.sh RUN) under the runs folder
RUN_RESULTS_DIR = "results"  # in a seed's run folder: scripts/benchmark.sh's RESULTS (evaluate --out)
RUN_TIMINGS_TSV = "timings.tsv"  # in a seed's run folder: scripts/benchmark.sh's steps, `total` last once it ended
SEED_RESULTS_DIR = SEED_RUN_DIR + "/" + RUN_RESULTS_DIR
ARCHIVE_DIR = "leaderboards/results/{name}-confirm"  # a freeze's archived seeds (each as SEED_RUN_DIR), committed
NOISY_ARCHIVE_DIR = "leaderboards/results/{name}-noisy-confirm"  # the same for its noisy-depth rows
ARCHIVE_README = SEED_RUN_DIR + "/README.md"  # what an archived seed holds (names and fold counts, no scores)
# the CPU of each archived fold record that does not name its own (made by a freeze from before records named it):
# {record path: {"model", "flags", "source"}}, the machine that archived it from its own run folder
ARCHIVE_MADE_ON = SEED_RUN_DIR + "/made_on.json"
ARCHIVED_DIRS = (SCORES_DIR, FAILED_DIR, REJECTED_DIR)  # the parts of a results folder that are fold records
# Paths that may change after the freeze without making it a new one: what is published, not what computes it.
UNFROZEN = ("leaderboards", "docs", "README.md")
DEVELOPMENT_SEEDS = frozenset({0, 1, 7, 11})  # used while choosing settings (1: the disjoint-object training set)
N_SEEDS = 3
BEGIN = "<!-- BEGIN CONFIRMATION (selfseg.eval.confirm; edits inside are overwritten) -->"
END = "<!-- END CONFIRMATION -->"
# A later freeze's section has markers of its own name, so every freeze of a preset stays on its page.
NAMED_BEGIN = "<!-- BEGIN CONFIRMATION {name} (selfseg.eval.confirm; edits inside are overwritten) -->"
NAMED_END = "<!-- END CONFIRMATION {name} -->"
# The protocol's rows, in the order shown; ``ours`` − each of the others is a claim.
BASELINES = ("supervised", "depth-clustering", "lccp-frame", "sdmaskrcnn-sim", "uois-sim", "fg-components")
ABLATIONS = ("ours-v2", "ours-v3", "ours-v4", "ours-paper-pruning")
TABLE2_ROWS = ("lccp", "lccp+symseg", "ours-matching", "gt-merging")
# Whose claims the board tests: ``ours``, or where it did not run (a preset whose matching does not terminate,
# e.g. ``cluttered``) V2, the self-supervised pipeline without matching; fixed here, never chosen after the seeds.
CLAIMANTS = ("ours", "ours-v2")
# A run that failed under its budget on a seed (a fold of it: ``failed/`` records) is shown failed on that seed and left
# out of the pooling there; a claim is then tested on the seeds where both sides ran every fold, and not at all when
# fewer than this many such seeds remain (fixed before any freeze whose runs have budgets).
MIN_CLAIM_SEEDS = 2


class FreezeError(ValueError):
    """The checkout or a result is not the freeze's; the message says what differs."""


def _git(*args: str) -> str:
    return subprocess.run(["git", "-C", str(ROOT), *args], capture_output=True, text=True, check=True).stdout.strip()


def fresh_seeds(commit: str, n: int = N_SEEDS, spent: frozenset[int] = frozenset()) -> list[int]:
    """``n`` dataset seeds in [100000, 1000000) derived from the freeze commit's hash, never a development seed nor
    one of ``spent`` (an earlier freeze's)."""
    seeds, k = [], 0
    while len(seeds) < n:
        s = 100_000 + int(hashlib.sha256(f"{commit}:{k}".encode()).hexdigest()[:12], 16) % 900_000
        if s not in DEVELOPMENT_SEEDS and s not in spent and s not in seeds:
            seeds.append(s)
        k += 1
    return seeds


def frozen_paths_differ(freeze_commit: str, commit: str) -> list[str]:
    """The files outside :data:`UNFROZEN` that differ between the two commits (empty: the same freeze)."""
    out = _git("diff", "--name-only", freeze_commit, commit, "--", ".", *(f":!{p}" for p in UNFROZEN))
    return out.splitlines()


def _freeze_name(preset: str, name: str | None) -> str:
    name = name or preset
    if not re.fullmatch(rf"{re.escape(preset)}(-[0-9]+)?", name):
        raise FreezeError(f"freeze name {name!r}: expected {preset!r} (the first) or {preset}-N (a later one)")
    return name


def spent_seeds(preset: str, but: str | None = None) -> frozenset[int]:
    """The fresh seeds of every recorded freeze of ``preset`` (except the one named ``but``)."""
    spent = set()
    for path in sorted((ROOT / "leaderboards").glob("*-freeze.json")):
        rec = read_json(path)
        if rec.get("preset") == preset and rec.get("name", preset) != but:
            spent.update(rec.get("seeds", []))
    return frozenset(spent)


def freeze(preset: str, n_seeds: int = N_SEEDS, name: str | None = None) -> dict:
    """Record the clean HEAD as the freeze ``name`` of ``preset`` (default: the preset's first); refuses a dirty
    tree or an existing record of that name. The seeds avoid every earlier freeze's of the preset."""
    name = _freeze_name(preset, name)
    path = ROOT / FREEZE_JSON.format(name=name)
    if path.exists():
        raise FreezeError(f"{path}: a freeze is already recorded; a new freeze is a new record "
                          f"(--freeze {preset}-N)")
    if _git("status", "--porcelain"):
        raise FreezeError("the working tree has uncommitted changes: commit them first, the freeze is a commit")
    commit = _git("rev-parse", "HEAD")
    configs = {p: hashlib.sha256((ROOT / p).read_bytes()).hexdigest()[:16]
               for p in _git("ls-files", "configs").splitlines()}
    rec = {"preset": preset, "name": name, "commit": commit,
           "committed_utc": _git("show", "-s", "--format=%cI", commit),
           "recorded_utc": datetime.now(timezone.utc).isoformat(timespec="seconds"),
           "seeds": fresh_seeds(commit, n_seeds, spent_seeds(preset, but=name)), "configs": configs}
    write_json(path, rec)
    return rec


def read_freeze(preset: str, name: str | None = None) -> dict:
    """The record of freeze ``name`` of ``preset`` (default: the preset's first), with its ``name`` filled in."""
    name = _freeze_name(preset, name)
    path = ROOT / FREEZE_JSON.format(name=name)
    rec = read_json(path)
    if rec.get("preset") != preset or not isinstance(rec.get("seeds"), list) or "commit" not in rec:
        raise FileFormatError(f"{path}: not a freeze record of preset {preset!r}")
    return {**rec, "name": rec.get("name", preset)}


def markers(rec: dict) -> tuple[str, str]:
    """The begin and end markers of freeze ``rec``'s section of the leaderboard page."""
    name = rec.get("name", rec["preset"])
    if name == rec["preset"]:
        return BEGIN, END
    return NAMED_BEGIN.format(name=name), NAMED_END.format(name=name)


def check_checkout(rec: dict) -> None:
    """Raise unless this checkout's code and configs are the freeze commit's and nothing is uncommitted."""
    head = _git("rev-parse", "HEAD")
    changed = frozen_paths_differ(rec["commit"], head)
    if changed:
        raise FreezeError(f"HEAD {head[:10]} differs from the freeze commit {rec['commit'][:10]} in "
                          f"{', '.join(changed[:5])}{' …' if len(changed) > 5 else ''}: that is a new freeze")
    dirty = uncommitted_frozen_paths()
    if dirty:
        raise FreezeError(f"uncommitted changes ({', '.join(dirty[:5])}): results would not name their code")


def uncommitted_frozen_paths() -> list[str]:
    """Files outside :data:`UNFROZEN` that are modified, staged or untracked in this checkout (a board written into
    ``leaderboards/`` while the seeds run is not one of them)."""
    paths = ("--", ".", *(f":!{p}" for p in UNFROZEN))
    changed = _git("diff", "--name-only", "HEAD", *paths).splitlines()
    untracked = _git("ls-files", "--others", "--exclude-standard", *paths).splitlines()
    return sorted(set(changed + untracked))


def _check_records(rec: dict, seed: int, groups: dict) -> None:
    for (_, name), recs in groups.items():
        for r in recs:
            commit = r["git"].get("commit") or "?"
            if r["git"].get("dirty") or commit == "?" or frozen_paths_differ(rec["commit"], commit):
                raise FreezeError(f"seed {seed}, run {name}, fold {r['fold']}: ran at {commit[:10]}"
                                  f"{' (dirty)' if r['git'].get('dirty') else ''}, not the freeze {rec['commit'][:10]}")


def _only_dataset(results: Path) -> dict:
    return _outcomes(results)[0]


def _outcomes(results: Path) -> tuple[dict, dict]:
    """(:func:`load_results` groups, :func:`load_failures` groups) of the one dataset in ``results``."""
    found = load_results(results)
    if len(found) != 1:
        raise FileFormatError(f"{results}: expected the results of one dataset, found {sorted(found) or 'none'}")
    key, groups = next(iter(found.items()))
    failures = load_failures(results)
    if set(failures) - {key}:
        raise FileFormatError(f"{results}: failure records of another dataset ({', '.join(sorted(set(failures) - {key}))})")
    return groups, failures.get(key, {})


def _split(label: str, development: bool, groups: dict, failures: dict | None = None) -> tuple[Seed, dict]:
    """One seed's results (:func:`load_results` groups of one dataset) and failures (:func:`load_failures` groups)
    as its 2-D :class:`Seed` (a run with a failed fold is in ``failed``, not ``runs``) and its 3-D runs (a failed
    row: its failure records)."""
    failures = failures or {}
    failed = {n: [r["fold"] for r in recs] for (t, n), recs in failures.items() if t == "2d"}
    three_d = {n: r for (t, n), r in groups.items() if t == "3d"}
    three_d.update({n: r for (t, n), r in failures.items() if t == "3d"})
    return (Seed(label, development, {n: r for (t, n), r in groups.items() if t == "2d" and n not in failed}, failed),
            three_d)


def _fresh(rec: dict, runs: Path) -> tuple[list[Seed], dict]:
    """(the fresh seeds with results under ``runs``, {label: 3-D groups}); every record is checked."""
    fresh, three_d = [], {}
    for s in rec["seeds"]:
        results = runs / SEED_RESULTS_DIR.format(seed=s)
        if not results.is_dir() or not _records(results):  # not begun, or no fold finished yet
            continue
        groups, failures = _outcomes(results)
        _check_records(rec, s, groups)
        _check_records(rec, s, failures)
        seed, three_d[seed.label] = _split(f"seed {s}", False, groups, failures)
        fresh.append(seed)
    return fresh, three_d


def _seeds(rec: dict, runs: Path, dev: list[tuple[str, Path]]) -> tuple[list[Seed], list[Seed], dict]:
    """(development seeds, fresh seeds with results, {label: 3-D groups}); fresh records are checked."""
    dev_seeds, three_d = [], {}
    for label, results in dev:
        seed, three_d[label] = _split(label, True, _only_dataset(results))
        dev_seeds.append(seed)
    fresh, fresh_3d = _fresh(rec, runs)
    return dev_seeds, fresh, {**three_d, **fresh_3d}


def _cell(videos: dict) -> str:
    if not videos:
        return "—"
    s = score(videos)
    return f"{fmt(s['mean'])} ({fmt(s['ci95'][0])}–{fmt(s['ci95'][1])})"


def _seed_cell(seed: Seed, name: str) -> str:
    """Run ``name`` on one seed: its score, or which folds failed under their budget."""
    if name in seed.failed:
        return f"failed: over budget (fold {', '.join(map(str, seed.failed[name]))})"
    return _cell(pooled_videos([seed], name))


def _pooled_cell(seeds: list[Seed], name: str) -> str:
    """Run ``name`` pooled over ``seeds``, saying how many seeds it holds when it failed on some."""
    cell = _cell(pooled_videos(seeds, name))
    lost = [s for s in seeds if name in s.failed]
    return f"{cell}, {len(seeds) - len(lost)} of {len(seeds)} seeds" if lost else cell


def _t2_cell(recs: list[dict] | None) -> str:
    """A Table II row on one seed: its IoU, "failed: over budget", or "—" (not run)."""
    if not recs:
        return "—"
    return "failed: over budget" if "failure" in recs[0] else fmt(recs[0]["metrics"]["IoU"])


def _attempted(seeds: list[Seed], name: str) -> bool:
    """``name`` ran, or failed under its budget, on one of ``seeds``."""
    return any(name in s.runs or name in s.failed for s in seeds)


def claim_row(a: str, b: str, seeds: list[Seed]) -> str:
    """The table row of claim ``a`` − ``b`` over the pooled ``seeds`` (their common test videos); where either
    failed under its budget on a seed, over the seeds where both ran, or "not tested" when fewer than
    :data:`MIN_CLAIM_SEEDS` remain."""
    lost = [s.label for s in seeds if a in s.failed or b in s.failed]
    both = [s for s in seeds if a in s.runs and b in s.runs]
    if lost and len(both) < MIN_CLAIM_SEEDS:
        who = " and ".join(n for n in (a, b) if any(n in s.failed for s in seeds))
        return (f"| {a} − {b} | — | — | — | **not tested**: {who} failed under its budget on {', '.join(lost)}, "
                f"{len(both)} seed{'s' * (len(both) != 1)} left (needs {MIN_CLAIM_SEEDS}) |")
    d = paired(pooled_videos(seeds, a), pooled_videos(seeds, b))
    where = f" ({len(both)} of {len(seeds)} seeds: a failure on {', '.join(lost)})" if lost else ""
    return (f"| {a} − {b} | {d['mean']:+.3f} | [{d['ci95'][0]:+.3f}, {d['ci95'][1]:+.3f}] | "
            f"{d['wins']} of {d['n_videos']}{where} | **{d['verdict']}** |")


def noise_markdown(rec: dict, fresh: list[Seed], three_d: dict, noisy: list[Seed], noisy_3d: dict) -> list[str]:
    """The noisy-depth subsection: each method on the fresh seeds with exact and with noisy depth (same scenes,
    masks and poses; RGB the same on one CPU type), the drop exact − noisy paired per test video, and ``ours``'s claims under noise."""
    labels = {s.label for s in noisy}
    exact = [s for s in fresh if s.label in labels]
    lines = ["", f"### The same seeds with noisy depth ({rec['preset']}-noisy)", "",
             f"The fresh seeds again with the depth-noise model on (`--depth-noise kinect`: the same scenes, masks "
             f"and poses, the depth a Kinect v1 would measure; the same RGB where both ran on one CPU type, since "
             f"Cycles' renders differ by a few 8-bit values between types), run with the same frozen configs, never tuned on "
             f"noise ({len(noisy)} of {len(rec['seeds'])} seeds finished). Drop = exact − noisy IoU per test video "
             "(same frames), 95 % CI by bootstrap over videos:", "",
             "| method | exact | noisy | drop | 95 % CI | videos worse with noise | verdict |", "|---|---|---|---|---|---|---|"]
    names = [n for n in ("ours", *BASELINES, *ABLATIONS) if pooled_videos(noisy, n) and pooled_videos(exact, n)]
    for n in names:
        a, b = pooled_videos(exact, n), pooled_videos(noisy, n)
        d = paired(a, b)
        common = set(a) & set(b)
        verdict = {"holds": "drops", "reversed": "rises"}.get(d["verdict"], d["verdict"])
        lines.append(f"| {n} | {fmt(frame_mean({v: a[v] for v in common}))} | {fmt(frame_mean({v: b[v] for v in common}))} "
                     f"| {d['mean']:+.3f} | [{d['ci95'][0]:+.3f}, {d['ci95'][1]:+.3f}] | {d['wins']} of {d['n_videos']} "
                     f"| {verdict} |")
    failed = [f"{n} on {s.label} (fold {', '.join(map(str, folds))})" for s in noisy for n, folds in s.failed.items()]
    if failed:
        lines += ["", f"Failed under their budget with noisy depth (left out of the drops there): {'; '.join(failed)}."]
    a = claimant(noisy)
    others = [o for o in (*BASELINES, *ABLATIONS) if a and o != a and _attempted(noisy, o)]
    if others:
        lines += ["", f"`{a}`'s claims with noisy depth (same protocol):", "",
                  "| claim | mean | 95 % CI | videos A > B | verdict |", "|---|---|---|---|---|"]
        lines += [claim_row(a, o, noisy) for o in others]
    t2 = [n for n in TABLE2_ROWS if any(n in noisy_3d.get(s.label, {}) for s in noisy)]
    if t2:
        lines += ["", "Table II IoU, exact → noisy depth, per seed:", "",
                  "| 3-D segmentation | " + " | ".join(s.label for s in noisy) + " |", "|---|" + "---|" * len(noisy)]
        for n in t2:
            cells = []
            for s in noisy:
                e, q = (_t2_cell(d.get(s.label, {}).get(n)) for d in (three_d, noisy_3d))
                cells.append(f"{e} → {q}")
            lines.append(f"| {n} | " + " | ".join(cells) + " |")
    return lines


def claimant(fresh: list[Seed]) -> str | None:
    """The first of :data:`CLAIMANTS` that ran in the fresh seeds, or failed there under its budget (its claims
    are then not tested, not handed to the next): None where neither ran."""
    return next((n for n in CLAIMANTS if _attempted(fresh, n)), None)


def board_markdown(rec: dict, dev_seeds: list[Seed], fresh: list[Seed], three_d: dict,
                   noise: list[str] | None = None) -> str:
    """The confirmation section (between :data:`BEGIN` and :data:`END`), with :func:`noise_markdown`'s lines
    when the noisy variant has run."""
    seeds = dev_seeds + fresh
    head = ([f"{s.label} (development)" for s in dev_seeds] + [s.label for s in fresh]
            + [f"pooled, {len(fresh)} fresh seeds"])
    names = [n for n in ("oracle", "ours", *BASELINES, *ABLATIONS) if _attempted(seeds, n)]
    name = rec.get("name", rec["preset"])
    begin, end = markers(rec)
    title = "## Confirmation on fresh seeds" + ("" if name == rec["preset"] else f": freeze `{name}`")
    lines = [begin, "", title, "",
             f"Freeze commit `{rec['commit'][:10]}` ({rec['committed_utc']}), recorded {rec['recorded_utc']} in "
             f"`{FREEZE_JSON.format(name=name)}`. Fresh seeds {', '.join(map(str, rec['seeds']))}: derived "
             f"from the freeze commit's hash, so no one saw their data before the freeze, and each ran once with the "
             f"frozen code and configs (every result record checked: {len(fresh)} of {len(rec['seeds'])} seeds "
             "finished). Development seeds are shown beside them and never pooled.", "",
             "IoU, mean over test frames (95 % CI, bootstrap over test videos):", "",
             "| method | " + " | ".join(head) + " |", "|---|" + "---|" * len(head)]
    for n in names:
        cells = [_seed_cell(s, n) for s in seeds] + [_pooled_cell(fresh, n)]
        lines.append(f"| {n} | " + " | ".join(cells) + " |")
    a = claimant(fresh)
    if a not in (None, CLAIMANTS[0]):
        lines += ["", f"`{CLAIMANTS[0]}` did not run on these seeds, so the claims below are `{a}`'s, the "
                  "self-supervised pipeline without matching across scenes."]
    budget_rule = (f" A run that failed under its budget on a seed is left out there; its claims are tested on the seeds "
                   f"where both sides ran every fold, and not at all with fewer than {MIN_CLAIM_SEEDS} such seeds."
                   if any(s.failed for s in fresh) else "")
    lines += ["", f"Paired differences over the pooled fresh seeds' test videos (IoU; A − B per video, weighted by "
              f"its frames; 95 % CI by bootstrap over videos). A claim holds only when its CI excludes 0.{budget_rule}",
              "",
              "| claim | mean | 95 % CI | videos A > B | verdict |"
              + (f" {'; '.join(s.label for s in dev_seeds)} (development) |" if dev_seeds else ""),
              "|---|---|---|---|---|" + ("---|" if dev_seeds else "")]
    for other in (*BASELINES, *ABLATIONS):
        if a is None or other == a or not _attempted(fresh, other):
            continue
        row = claim_row(a, other, fresh)
        if dev_seeds:
            dv = [paired(pooled_videos([s], a), pooled_videos([s], other)) for s in dev_seeds
                  if pooled_videos([s], a) and pooled_videos([s], other)]
            row += " " + ("; ".join(f"{x['mean']:+.3f} [{x['ci95'][0]:+.3f}, {x['ci95'][1]:+.3f}]" for x in dv) or "—") + " |"
        lines.append(row)
    sup = pooled_videos(fresh, "supervised")
    if sup:
        s = score(sup)
        lines += ["", f"Supervised bound, pooled: {fmt(s['mean'])} (CI {fmt(s['ci95'][0])}–{fmt(s['ci95'][1])}); "
                  f"target ≥ .90: {'met' if s['mean'] >= 0.90 else 'missed'}."]
    t2 = [n for n in TABLE2_ROWS if any(n in g for g in three_d.values())]
    if t2:
        labels = [s.label for s in seeds]
        lines += ["", "Table II (3-D, all videos of each seed; IoU over points, mean over videos' frames as in Table II):", "",
                  "| 3-D segmentation | " + " | ".join(labels) + " |", "|---|" + "---|" * len(labels)]
        for n in t2:
            lines.append(f"| {n} | " + " | ".join(_t2_cell(three_d.get(label, {}).get(n)) for label in labels) + " |")
    return "\n".join(lines + (noise or []) + ["", end]) + "\n"


def board(rec: dict, runs: Path, dev: list[tuple[str, Path]], out: Path, noisy_runs: Path | None = None) -> Path:
    """Write the confirmation section of freeze ``rec`` into ``out`` (text outside its markers is kept);
    ``noisy_runs``: the same fresh seeds of the preset's noisy variant, run from the freeze (same layout)."""
    dev_seeds, fresh, three_d = _seeds(rec, runs, dev)
    noise = None
    if noisy_runs is not None:
        noisy, noisy_3d = _fresh(rec, noisy_runs)
        noise = noise_markdown(rec, fresh, three_d, noisy, noisy_3d) if noisy else None
    text = board_markdown(rec, dev_seeds, fresh, three_d, noise)
    atomic_write_text(out, replace_generated(out.read_text() if out.is_file() else None, text,
                                             f"Leaderboard: {rec['preset']}", *markers(rec)))
    return out


def _records(results: Path) -> list[Path]:
    """The finished fold records under a results folder, relative to it: each fold's JSON (scores, failure or
    rejection) and its per-frame lines; a frame file whose fold JSON is not written yet is a fold still running."""
    out = []
    for top in ARCHIVED_DIRS:
        for path in sorted((results / top).rglob("fold*.json")):
            out.append(path.relative_to(results))
            frames = path.with_name(path.name.removesuffix(".json") + ".frames.jsonl")
            if frames.is_file():
                out.append(frames.relative_to(results))
    return out


def _seed_readme(rec: dict, seed: int, run: Path, noisy: bool, made_on: dict) -> str:
    """An archived seed's README: its state, dataset, runs (names and fold counts; no score is read) and the CPUs
    its records were made on (their own field, else ``made_on``: :data:`ARCHIVE_MADE_ON`'s entries)."""
    runs, hashes, cpus = {}, set(), set()
    for m in made_on.values():
        cpus.add(f"{m['model']} ({', '.join(m['flags']) or 'no listed flags'}; {m['source']})")
    for f in _records(run / RUN_RESULTS_DIR):
        if f.suffix == ".json":
            r = read_json(run / RUN_RESULTS_DIR / f)
            hashes.add(r.get("dataset", {}).get("content_hash", "?")[:16])
            if "cpu" in r:  # records since the CPU was recorded
                cpus.add(f"{r['cpu']['model']} ({', '.join(r['cpu']['flags']) or 'no listed flags'})")
            counts = runs.setdefault(f.parts[2], {})  # <top>/<dataset>/<name>/fold<k>.json
            counts[f.parts[0]] = counts.get(f.parts[0], 0) + 1
    timings = run / RUN_TIMINGS_TSV
    rows = timings.read_text().splitlines() if timings.is_file() else []
    state = ("**finished**" if rows and rows[-1].startswith("total\t")
             else "**not finished** (the run was cut off or is still going)")
    if noisy:  # scripts/confirm_noisy.sh keeps no timings: the records say what had finished, not whether all had
        state = "with the runs' records that had finished (the noisy rows keep no timings to tell the seed's end)"
    listed = "; ".join(f"`{n}` " + ", ".join(f"{c[d]} {'scored' if d == SCORES_DIR else d}" for d in ARCHIVED_DIRS
                                             if d in c) for n, c in sorted(runs.items()))
    now = datetime.now(timezone.utc).strftime("%Y-%m-%d %H:%M UTC")
    return (f"Seed {seed} of the `{rec['name']}` freeze ({rec['commit'][:7]}), {state} when archived ({now}) by "
            f"`python -m selfseg.eval.confirm archive`: the fold records of its run, copied from the run folder.\n"
            f"Dataset content hash {', '.join(sorted(hashes)) or '(no record yet)'}. Records: {listed or 'none'}.\n"
            + (f"Made on: {'; '.join(sorted(cpus))}.\n" if cpus else "") +
            f"To go on with it on another machine: `{'NOISY=1 ' if noisy else ''}scripts/confirm_resume.sh {rec['preset']} {rec['name']} CLONE RUNS` "
            f"(restores these records and keeps them where the regenerated data has the same content hash, which "
            f"takes a CPU of the type that made them: Cycles' RGB differs on another, docs/reproducibility.md).\n"
            f"Archiving reads names and fold counts only, no score.\n")


def _copy(src: Path, dst: Path, paths: list[Path], replace: bool) -> list[Path]:
    """Copy ``paths`` (relative, files that exist under ``src``) to ``dst``, each atomically: every one that
    differs there when ``replace``, else only those ``dst`` lacks. Returns the paths written."""
    written = []
    for f in paths:
        data = (src / f).read_bytes()
        if not (dst / f).is_file() or (replace and (dst / f).read_bytes() != data):
            atomic_write_bytes(dst / f, data)
            written.append(f)
    return written


def _seed_files(run: Path) -> list[Path]:
    """What is archived of one seed's run folder, relative to it: the fold records and the timings."""
    records = [RUN_RESULTS_DIR / f for f in _records(run / RUN_RESULTS_DIR)]
    return records + ([Path(RUN_TIMINGS_TSV)] if (run / RUN_TIMINGS_TSV).is_file() else [])


def archive(rec: dict, runs: Path, dest: Path, noisy: bool = False) -> list[str]:
    """Copy the finished fold records of freeze ``rec``'s seeds under ``runs`` (``noisy``: its noisy-depth rows) into
    ``dest`` (one folder per seed, with a README); refuses to drop a record ``dest`` already holds that ``runs`` lacks (restore first).
    A record ``dest`` holds of the same run (:func:`_run_identity`) stays as it is. Returns one line per seed archived."""
    lines = []
    for s in rec["seeds"]:
        run, into = runs / SEED_RUN_DIR.format(seed=s), dest / SEED_RUN_DIR.format(seed=s)
        if not (run / RUN_RESULTS_DIR).is_dir():
            continue
        files = _seed_files(run)
        lost = sorted(set(_seed_files(into)) - set(files))
        if lost:
            raise FreezeError(f"{into / lost[0]}: archived but not in {run} ({len(lost)} such files); "
                              f"run `confirm restore` into that runs folder first")
        if not files:  # nothing finished yet: no folder for it
            continue
        kept = [f for f in files if f.suffix == ".json" and (into / f).is_file()
                and _run_identity(read_json(into / f)) == _run_identity(read_json(run / f))]
        kept += [f.with_name(f.name.removesuffix(".json") + ".frames.jsonl") for f in kept]
        written = _copy(run, into, [f for f in files if f not in kept], replace=True)
        made_on_json = dest / ARCHIVE_MADE_ON.format(seed=s)
        made_on = read_json(made_on_json) if made_on_json.is_file() else {}
        here = {"model": cpu_model(), "flags": cpu_flags(), "source": "the machine that archived it from its run"}
        # a record written here, not restored (a restored one is kept), was made on this machine; an entry of a
        # record replaced by one that names its CPU goes
        records = [f for f in written if f.suffix == ".json"]
        new = {k: v for k, v in made_on.items() if k not in {f.as_posix() for f in records}}
        new |= {f.as_posix(): here for f in records if "cpu" not in read_json(run / f)}
        if new != made_on:
            made_on = new
            write_json(made_on_json, made_on)
        readme = dest / ARCHIVE_README.format(seed=s)
        if written or not readme.is_file():
            atomic_write_text(readme, _seed_readme(rec, s, run, noisy, made_on))
        lines.append(f"seed {s}: {sum(f.suffix == '.json' for f in files)} fold records → {into}")
    return lines


def _run_identity(record: dict) -> dict:
    """What makes two fold records the same run's: :func:`~selfseg.eval.provenance.run_key`, name and fold. An
    archived record keeps its place when a rerun of the same run (a resumed queue re-scoring a finished step)
    writes it again with a new time stamp and timings: the record of a fresh seed is its first run's."""
    return {**run_key(record), "name": record.get("name"), "fold": record.get("fold")}


def restore(rec: dict, src: Path, runs: Path) -> list[str]:
    """Copy the archived fold records of freeze ``rec``'s seeds from ``src`` into ``runs`` (files already there
    are left as they are: the runs folder is the newer). Returns one line per seed restored."""
    lines = []
    for s in rec["seeds"]:
        archived, into = src / SEED_RUN_DIR.format(seed=s), runs / SEED_RUN_DIR.format(seed=s)
        if archived.is_dir():
            new = _copy(archived, into, _seed_files(archived), replace=False)
            lines.append(f"seed {s}: {sum(f.suffix == '.json' for f in new)} fold records restored → {into}")
    return lines


def compare_lines(results: Path, a: str, others: list[str]) -> list[str]:
    """``a`` − each of ``others`` on one results folder's test videos (one seed), as :func:`paired` reads it."""
    groups = _only_dataset(results)
    seed, _ = _split("", False, groups)
    mine = pooled_videos([seed], a)
    if not mine:
        raise FileFormatError(f"{results}: no 2-D results of {a!r}")
    lines = []
    for other in others:
        theirs = pooled_videos([seed], other)
        if not theirs:
            raise FileFormatError(f"{results}: no 2-D results of {other!r}")
        d = paired(mine, theirs)
        lines.append(f"{a} − {other}: {d['mean']:+.3f} IoU, 95 % CI [{d['ci95'][0]:+.3f}, {d['ci95'][1]:+.3f}] over "
                     f"{d['n_videos']} test videos ({d['wins']} won): {d['verdict']}")
    return lines


def against_lines(results: Path, against: Path) -> list[str]:
    """Every 2-D run in both folders (the same dataset, e.g. one seed run by two commits): its IoU in ``results``
    − in ``against``, paired over the same test videos; a run in one folder only is named, not compared."""
    new, old = (_split("", False, _only_dataset(r))[0] for r in (results, against))
    both = [n for n in new.runs if n in old.runs]
    if not both:
        raise FileFormatError(f"{results}, {against}: no 2-D run in both")
    lines = []
    for n in both:
        a, b = pooled_videos([new], n), pooled_videos([old], n)
        d = paired(a, b)
        lines.append(f"{n}: {fmt(frame_mean(a))} − {fmt(frame_mean(b))} = {d['mean']:+.3f} IoU, 95 % CI "
                     f"[{d['ci95'][0]:+.3f}, {d['ci95'][1]:+.3f}] over {d['n_videos']} test videos: {d['verdict']}")
    only = sorted(set(new.runs) ^ set(old.runs))
    return lines + ([f"in one folder only: {', '.join(only)}"] if only else [])


def _dev_arg(text: str) -> tuple[str, Path]:
    label, sep, path = text.partition("=")
    if not sep or not label or not path:
        raise argparse.ArgumentTypeError(f"{text!r}: expected LABEL=RESULTS_DIR, e.g. 'seed 0=leaderboards/results/calibrated'")
    return label, Path(path)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m selfseg.eval.confirm", description=__doc__.splitlines()[0])
    p.add_argument("command", choices=("freeze", "seeds", "check", "board", "compare", "archive", "restore"))
    p.add_argument("--preset", default="calibrated")
    p.add_argument("--freeze", metavar="NAME", help="which freeze of the preset: the preset's name for the first "
                   "(default), <preset>-2 and so on for later ones")
    p.add_argument("--n-seeds", type=int, default=N_SEEDS, help="freeze: how many fresh seeds")
    p.add_argument("--runs", type=Path, default=Path("runs/confirm"),
                   help="board, archive, restore: the folder holding each fresh seed's run (seed-<S>/results)")
    p.add_argument("--dev", type=_dev_arg, action="append", default=[], metavar="LABEL=RESULTS",
                   help="board: a development seed's results folder, shown beside the fresh seeds (repeatable)")
    p.add_argument("--noisy-runs", type=Path,
                   help="board: the same fresh seeds of the preset's noisy variant (seed-<S>/results), run from the freeze")
    p.add_argument("--noisy", action="store_true", help="archive, restore: the runs are the noisy-depth rows "
                   f"(scripts/confirm_noisy.sh; archived in {NOISY_ARCHIVE_DIR.format(name='<freeze>')})")
    p.add_argument("--out", type=Path, help="board: the leaderboard page (default leaderboards/<preset>.md)")
    p.add_argument("--results", type=Path, help="compare: one dataset's results folder (evaluate --out)")
    p.add_argument("--a", default="ours", help="compare: the run whose claims are tested (default ours)")
    p.add_argument("--b", action="append", default=[], metavar="NAME",
                   help="compare: a run to compare against, paired over the same test videos (repeatable)")
    p.add_argument("--against", type=Path, metavar="RESULTS",
                   help="compare: another results folder of the same data; every run in both, --results − --against")
    args = p.parse_args(argv)
    if args.command == "compare" and (args.results is None or bool(args.b) == bool(args.against)):
        p.error("compare needs --results and either at least one --b or --against")
    try:
        if args.command == "freeze":
            rec = freeze(args.preset, args.n_seeds, args.freeze)
            print(f"freeze of {args.preset}: commit {rec['commit'][:10]}, seeds {' '.join(map(str, rec['seeds']))}; "
                  f"commit {FREEZE_JSON.format(name=rec['name'])} now")
        elif args.command == "seeds":
            print("\n".join(map(str, read_freeze(args.preset, args.freeze)["seeds"])))
        elif args.command == "check":
            check_checkout(read_freeze(args.preset, args.freeze))
        elif args.command in ("archive", "restore"):
            rec = read_freeze(args.preset, args.freeze)
            dest = ROOT / (NOISY_ARCHIVE_DIR if args.noisy else ARCHIVE_DIR).format(name=rec["name"])
            print("\n".join(archive(rec, args.runs, dest, args.noisy) if args.command == "archive" else restore(rec, dest, args.runs))
                  or f"no seed of freeze {rec['name']} under {args.runs if args.command == 'archive' else dest}")
        elif args.command == "compare":
            print("\n".join(against_lines(args.results, args.against) if args.against
                             else compare_lines(args.results, args.a, args.b)))
        else:
            print(board(read_freeze(args.preset, args.freeze), args.runs, args.dev,
                        args.out or ROOT / "leaderboards" / f"{args.preset}.md", args.noisy_runs))
    except (FreezeError, FileFormatError, FileNotFoundError) as e:
        print(f"confirm: error: {e}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
