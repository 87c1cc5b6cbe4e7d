"""Results pooled over several seeds of a preset, and paired differences between methods with bootstrap CIs.

The confirmation protocol's statistics (``scripts/confirm.sh``). Each seed is its own dataset; a method's score
pooled over seeds is the mean over every test frame of every seed and fold (the paper's "dataset score averages
over frames", extended over seeds). A paired difference A − B compares the two methods on the same test videos:
per video the difference of their frame means, weighted by the video's frames (both scored the same frames, which
is checked), resampled over videos for the 95 % CI (:func:`selfseg.eval.aggregate.bootstrap_ci`). A claim
*holds* only when its CI excludes 0 on the claimed side.
"""
from __future__ import annotations

from dataclasses import dataclass, field

from selfseg.eval.aggregate import bootstrap_ci

KEY = "IoU"  # the metric the protocol's claims are about


@dataclass
class Seed:
    """One seed's 2-D runs: ``runs[name]`` = that run's fold records (see :mod:`selfseg.eval.protocol`; layout: :mod:`selfseg.eval.layout`)."""

    label: str  # e.g. "seed 184467"
    development: bool  # a development seed is reported beside the fresh ones, never pooled
    runs: dict[str, list[dict]]
    # run name → its folds that failed under their budget; such a run is not in ``runs`` (not pooled on this seed)
    failed: dict[str, list[int]] = field(default_factory=dict)


def _videos(seed: Seed, name: str, key: str) -> dict[str, dict]:
    """``{"<seed label>/<video>": {key, n_frames}}`` of one run of one seed, every fold's test videos."""
    out = {}
    for rec in seed.runs.get(name, []):
        for vid, m in rec["per_video"].items():
            if m["n_frames"] > 0:
                out[f"{seed.label}/{vid}"] = {key: m[key], "n_frames": m["n_frames"]}
    return out


def pooled_videos(seeds: list[Seed], name: str, key: str = KEY) -> dict[str, dict]:
    """The test videos of ``name`` over every seed in ``seeds``."""
    return {v: m for s in seeds for v, m in _videos(s, name, key).items()}


def frame_mean(videos: dict[str, dict], key: str = KEY) -> float:
    """Mean of ``key`` over the frames of ``videos`` (each video's mean weighted by its frames)."""
    n = sum(m["n_frames"] for m in videos.values())
    return sum(m[key] * m["n_frames"] for m in videos.values()) / n if n else float("nan")


def score(videos: dict[str, dict], key: str = KEY) -> dict:
    """{mean (over frames), ci95 (bootstrap over videos), n_videos, n_frames} of a pooled run."""
    return {"mean": frame_mean(videos, key), "ci95": bootstrap_ci(videos, (key,))[key], "n_videos": len(videos),
            "n_frames": sum(m["n_frames"] for m in videos.values())}


def paired(a: dict[str, dict], b: dict[str, dict], key: str = KEY) -> dict:
    """A − B on their common test videos: {mean, ci95, n_videos, wins (videos where A > B), losses, verdict}.

    ``verdict``: "holds" (CI above 0), "reversed" (CI below 0) or "inside the noise". A video that both scored
    on different numbers of frames is an error (the runs did not use the same frames); a video only one of them
    scored is left out and counted in ``n_unpaired``."""
    common = sorted(set(a) & set(b))
    for v in common:
        if a[v]["n_frames"] != b[v]["n_frames"]:
            raise ValueError(f"video {v}: scored on {a[v]['n_frames']} and {b[v]['n_frames']} frames; "
                             "a paired difference needs the same frames")
    diff = {v: {key: a[v][key] - b[v][key], "n_frames": a[v]["n_frames"]} for v in common}
    lo, hi = bootstrap_ci(diff, (key,))[key] if diff else (float("nan"), float("nan"))
    verdict = "holds" if lo > 0 else "reversed" if hi < 0 else "inside the noise"
    return {"mean": frame_mean(diff, key), "ci95": [lo, hi], "n_videos": len(diff),
            "wins": sum(d[key] > 0 for d in diff.values()), "losses": sum(d[key] < 0 for d in diff.values()),
            "n_unpaired": len(set(a) ^ set(b)), "verdict": verdict}
