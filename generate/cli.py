"""``generate_scenes``: generate a dataset of orbiting RGB-D videos of physics-dropped objects.

Scenes are written atomically (temporary folder, then rename), so an interrupted run resumes:
completed scenes are skipped; a scene whose Ray worker died is re-run by Ray (``--executor ray``).
The output folder must be empty, absent, or this same dataset (same resolved config); ``--overwrite``
replaces an existing selfseg dataset. Bad input exits with code 2 and a message naming the problem,
before anything is written.
"""
from __future__ import annotations

import argparse
import concurrent.futures as cf
import contextlib
import multiprocessing
import os
import re
import shutil
import socket
import sys
import time
from pathlib import Path

from tqdm import tqdm

from selfseg.config import ConfigError, from_dict, to_dict
from selfseg.dataset import (DATASET_INFO, DEPTH, MASK_INST, MODELS_DIR, MODELS_INFO, RGB, SCENE_CAMERA, SCENE_GT,
                             SCENE_INFO, VIDEO_DIR, VIDEOS_DIR, DatasetError, geometry_hash, is_rgb_frame,
                             only_rgb_differs, video_id_str)
from selfseg.executor import EXECUTORS, ExecutorError, check_shared_folder, executor_config, make_executor
from selfseg.fileio import FileFormatError, hash_json, read_json, write_json
from selfseg.generate.determinism import is_pinned, pinned_vars, reexec_pinned, start_environ
from selfseg.generate.objects import write_models
from selfseg.generate.presets import GENERATOR_VERSION, LIBRARIES, PRESETS, GenerateConfig, preset_config
from selfseg.generate.scene import STAGES, generate_scene, load_library, orbit_step_deg
from selfseg.manifest import MANIFEST, differences, manifest_hash, read_manifest, write_manifest
from selfseg.writers import write_dataset_info

PROGRESS_FILE = ".generate.json"  # config of a generation in progress; removed when the dataset is complete
EXIT_BAD_INPUT = 2
EXIT_RGB_ONLY = 3  # --verify: only RGB frames differ from the manifest


class GenerateError(ValueError):
    """Bad command-line input or output folder; the message says what and where."""


def _resolution(text: str) -> tuple[int, int]:
    m = re.fullmatch(r"\s*(\d+)\s*[xX]\s*(\d+)\s*", text)
    if not m:
        raise argparse.ArgumentTypeError(f"resolution must look like 320x240, got {text!r}")
    return int(m.group(1)), int(m.group(2))


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="generate_scenes", description=__doc__.split("\n")[0])
    p.add_argument("--preset", choices=list(PRESETS), default="tiny", help="base configuration (default: tiny)")
    p.add_argument("--out", type=Path, help="dataset folder to create or resume (required unless --verify)")
    p.add_argument("--scenes", type=int, help="number of scenes (videos)")
    p.add_argument("--frames", type=int, help="frames per full-rate video")
    p.add_argument("--frame-step", type=int, help="render only every n-th frame (frame ids keep the full-rate index)")
    p.add_argument("--resolution", type=_resolution, help="image size WxH, e.g. 320x240")
    p.add_argument("--objects-per-scene", type=int, help="objects dropped per scene")
    p.add_argument("--objects", type=Path, help="folder of user meshes (OBJ/PLY/GLB, metres) instead of the builtin library")
    p.add_argument("--library", choices=list(LIBRARIES), help="object library built in code: builtin (25 objects) or "
                   "paper (chunky multi-part toys); default: the preset's")
    p.add_argument("--renderer", choices=["cycles", "workbench"], help="image renderer (default: cycles)")
    p.add_argument("--depth-noise", choices=["off", "kinect"], help="sensor noise on the depth frames: off (exact depth) "
                   "or kinect (structured light, generate/depth_noise.py); masks and poses stay exact; default: the "
                   "preset's")
    p.add_argument("--object-pool", type=lambda v: [n.strip() for n in v.split(",") if n.strip()],
                   help="comma-separated object names to draw from (e.g. a set disjoint from another dataset's, "
                        "for the v1-disjoint baseline); default: the preset's pool")
    p.add_argument("--seed", type=int, help="dataset seed (default 0)")
    p.add_argument("--workers", type=int, default=1, help="scenes rendered in parallel processes (default 1); "
                   "with --executor ray and no --ray-address, the CPUs of the Ray instance started for the run")
    p.add_argument("--executor", default="local", help=f"where scenes render: {' or '.join(EXECUTORS)} "
                   "(Ray tasks, one per scene; default local)")
    p.add_argument("--ray-address", help="join this Ray cluster (auto or HOST:PORT) instead of starting a local "
                   "instance; --out must be on a filesystem every node sees")
    p.add_argument("--ray-cpus-per-task", type=float, default=1, help="CPUs each scene's Ray task reserves (default 1)")
    p.add_argument("--ray-gpus-per-task", type=float, default=0,
                   help="GPUs each scene's Ray task reserves, for Cycles on GPU nodes (default 0: CPU rendering)")
    p.add_argument("--overwrite", action="store_true", help="replace an existing selfseg dataset in --out")
    p.add_argument("--cache-dir", type=Path, default=Path(os.environ.get("SELFSEG_CACHE", Path.home() / ".cache" / "selfseg")),
                   help="cache for collision decompositions (default ~/.cache/selfseg or $SELFSEG_CACHE)")
    p.add_argument("--quiet", action="store_true", help="no progress bars")
    p.add_argument("--verify", type=Path, metavar="DIR", help="check every byte of the dataset DIR against its "
                   "manifest.json and print its manifest hash (exit 1 if it differs, 3 if only RGB frames differ, as "
                   "on another CPU type); generates nothing")
    return p


def verify_dataset(root: Path) -> int:
    """``--verify DIR``: one line; 0 if every file matches the manifest, 3 if only RGB frames differ (the class of
    difference another CPU type gives: :func:`selfseg.dataset.only_rgb_differs`), 1 if anything else differs, 2 without a manifest."""
    try:
        stored, found = differences(root, full=True)
    except (FileNotFoundError, FileFormatError) as e:
        print(f"generate_scenes: error: {e}", file=sys.stderr)
        return EXIT_BAD_INPUT
    digest, geometry = manifest_hash(stored), geometry_hash(stored)
    if only_rgb_differs(found):
        n_rgb = sum(map(is_rgb_frame, stored))
        print(f"{root}: every file but the RGB frames matches manifest {digest} (geometry hash {geometry}); "
              f"{len(found)} of {n_rgb} RGB frames differ, the class of difference rendering on another CPU type "
              f"gives (Cycles and OpenImageDenoise pick SIMD kernels by CPU: a few 8-bit values per frame differ by "
              f"1); verify cannot tell it from edited RGB")
        return EXIT_RGB_ONLY
    if found:
        first = next((p for p in found if not is_rgb_frame(p)), next(iter(found)))  # what is not render noise
        problem = found[first]
        more = f" (and {len(found) - 1} more differences)" if len(found) > 1 else ""
        print(f"generate_scenes: {root / first}: {problem}{more}; {root} is not the data of manifest {digest}",
              file=sys.stderr)
        return 1
    print(f"{root}: every file matches manifest {digest} (geometry hash {geometry})")
    return 0


def config_from_args(args: argparse.Namespace) -> GenerateConfig:
    """The resolved config: the preset, then the command-line overrides."""
    width, height = args.resolution if args.resolution else (None, None)
    render = {"renderer": args.renderer} if args.renderer else {}
    if args.depth_noise is not None:
        render["depth_noise"] = {} if args.depth_noise == "kinect" else None  # {}: DepthNoiseConfig's defaults
    return preset_config(args.preset, scenes=args.scenes, frames=args.frames, frame_step=args.frame_step,
                         width=width, height=height, objects_per_scene=args.objects_per_scene,
                         objects_dir=str(args.objects.resolve()) if args.objects else None, seed=args.seed,
                         object_pool=args.object_pool, library=args.library, render=render or None)


def _without_noise_off(config: dict) -> dict:
    """A config record without ``render.depth_noise`` when that is None (off)."""
    render = config.get("render")
    if isinstance(render, dict) and "depth_noise" in render and render["depth_noise"] is None:
        return {**config, "render": {k: v for k, v in render.items() if k != "depth_noise"}}
    return config


def recorded_config(cfg: GenerateConfig) -> dict:
    """The config as dataset_info.json records it: without ``render.depth_noise`` when it is off, so that data
    made without noise keeps the bytes (and manifest hash) it had before the option existed."""
    return _without_noise_off(to_dict(cfg))


def _stored_config(out: Path) -> dict | None:
    """The config (with the generator version) recorded in an existing dataset folder, finished or
    in progress; None if there is none."""
    for name in (DATASET_INFO, PROGRESS_FILE):
        if (out / name).is_file():
            try:
                rec = read_json(out / name)
                return {**rec["config"], "generator_version": rec["generator_version"]}
            except (FileFormatError, KeyError, TypeError):
                raise GenerateError(f"{out / name}: unreadable dataset record; use --overwrite to replace it") from None
    return None


def _foreign_entries(out: Path, cfg: GenerateConfig) -> list[str]:
    """Entries of ``out`` that this dataset would not have written."""
    scene_names = {video_id_str(i) for i in range(cfg.scenes)}
    foreign = [p.name for p in out.iterdir() if p.name not in (DATASET_INFO, PROGRESS_FILE, MANIFEST, MODELS_DIR,
                                                                VIDEOS_DIR)]
    videos = out / VIDEOS_DIR
    if videos.is_dir():
        foreign += [f"{VIDEOS_DIR}/{p.name}" for p in videos.iterdir()
                    if p.name not in scene_names and not re.fullmatch(r"\.\d{6}\..*\.partial", p.name)]
    return sorted(foreign)


# a video folder's entries in the dataset format: rgb, depth, mask_inst and the three JSON records
VIDEO_ENTRIES = {Path(t.format(video_id="0", frame_id=0)).parts[2]: t for t in
                 (RGB, DEPTH, MASK_INST, SCENE_CAMERA, SCENE_GT, SCENE_INFO)}
FRAME_FOLDERS = sorted(e for e, t in VIDEO_ENTRIES.items() if "{frame_id" in t)


def _video_folders(out: Path) -> list[Path]:
    """The six-digit video folders of ``out``, sorted."""
    videos = out / VIDEOS_DIR
    return sorted(p for p in videos.iterdir() if re.fullmatch(r"\d{6}", p.name)) if videos.is_dir() else []


def _user_files_in_videos(out: Path) -> list[str]:
    """Files inside video folders that the dataset format does not own (``out``-relative): entries besides
    :data:`VIDEO_ENTRIES`, and anything in rgb/, depth/, mask_inst/ but six-digit PNG frames."""
    found = []
    for v in _video_folders(out):
        for p in sorted(v.iterdir()):
            if p.name not in VIDEO_ENTRIES:
                found.append(p)
            elif p.name in FRAME_FOLDERS and p.is_dir():
                found += [q for q in sorted(p.iterdir()) if not re.fullmatch(r"\d{6}\.png", q.name)]
    return [str(p.relative_to(out)) for p in found]


def _scene_missing(video_dir: Path, cfg: GenerateConfig) -> str | None:
    """What a finished scene of ``cfg`` lacks in ``video_dir`` (its first missing file), None if complete."""
    vid = video_dir.name
    need = [t.format(video_id=vid, frame_id=f) for t in VIDEO_ENTRIES.values() if "{frame_id" in t
            for f in cfg.frame_ids]
    need += [t.format(video_id=vid) for t in VIDEO_ENTRIES.values() if "{frame_id" not in t]
    root = video_dir.parent.parent
    return next((rel for rel in need if not (root / rel).is_file()), None)


def remove_dataset(out: Path) -> list[str]:
    """Delete what the dataset format owns in ``out`` (dataset_info.json, the progress record, manifest.json,
    models/obj_*.ply and models_info.json, and per six-digit video folder its rgb/, depth/, mask_inst/ and JSON
    records, plus interrupted scenes); folders left empty go too. Any other file stays. Returns what was removed."""
    owned = [out / DATASET_INFO, out / PROGRESS_FILE, out / MANIFEST, out / MODELS_INFO]
    owned += sorted((out / MODELS_DIR).glob("obj_[0-9][0-9][0-9][0-9][0-9][0-9].ply"))
    videos = out / VIDEOS_DIR
    owned += sorted(videos.glob(".*.partial")) if videos.is_dir() else []
    video_dirs = _video_folders(out)
    owned += [v / e for v in video_dirs for e in sorted(VIDEO_ENTRIES)]
    removed = []
    for path in owned:
        if path.is_dir() and not path.is_symlink():
            shutil.rmtree(path)
        elif path.exists() or path.is_symlink():
            path.unlink()
        else:
            continue
        removed.append(str(path.relative_to(out)))
    for folder in [*video_dirs, videos, out / MODELS_DIR]:  # only if nothing of the user's is inside
        if folder.is_dir() and not any(folder.iterdir()):
            folder.rmdir()
    return removed


def prepare_output(out: Path, cfg: GenerateConfig, overwrite: bool) -> None:
    """Check ``out`` is absent, empty, or this same dataset; with ``overwrite`` replace a selfseg dataset.

    Raises GenerateError before anything is written or deleted if the folder cannot be used. ``overwrite``
    deletes only what the dataset format owns (:func:`remove_dataset`) and says how much it removed.
    """
    if out.exists() and not out.is_dir():
        raise GenerateError(f"{out}: exists and is not a folder")
    if not out.exists() or not any(out.iterdir()):
        return
    stored = _stored_config(out)
    if overwrite:
        if stored is None:
            raise GenerateError(f"{out}: not a selfseg dataset (no {DATASET_INFO}); refusing to delete it even with "
                                "--overwrite. Choose another --out or empty the folder yourself")
        inside = _user_files_in_videos(out)
        if inside:  # emptying that video would leave a folder that looks finished but holds no scene
            raise GenerateError(f"{out / inside[0]}: a file generate_scenes did not write is inside a video folder "
                                f"({len(inside)} such files); --overwrite would empty that video. Move them out of "
                                f"{out / VIDEOS_DIR} first")
        removed = remove_dataset(out)
        kept = sorted(p.name for p in out.iterdir())
        print(f"generate_scenes: --overwrite removed {len(removed)} dataset entries from {out} "
              f"({', '.join(removed[:4])}{', …' if len(removed) > 4 else ''})"
              + (f"; kept files it does not own: {', '.join(kept[:5])}" if kept else ""), file=sys.stderr)
        return
    if stored is None:
        raise GenerateError(f"{out}: folder is not empty and is not a selfseg dataset; choose another --out")
    stored = _without_noise_off(stored)  # a record that spells the noise out as off is the same config
    ours = {**recorded_config(cfg), "generator_version": GENERATOR_VERSION}
    if hash_json(stored) != hash_json(ours):
        diff = sorted(k for k in set(ours) | set(stored if isinstance(stored, dict) else {})
                      if not isinstance(stored, dict) or stored.get(k) != ours.get(k))
        raise GenerateError(f"{out}: holds a dataset generated with a different config (differs in: "
                            f"{', '.join(diff) or 'format'}); use --overwrite to replace it or choose another --out")
    foreign = _foreign_entries(out, cfg)
    if foreign:
        raise GenerateError(f"{out}: contains files this dataset did not write ({', '.join(foreign[:5])}); "
                            "remove them or choose another --out")
    for i in range(cfg.scenes):  # a scene folder counts as done only when it is complete
        folder = out / VIDEO_DIR.format(video_id=video_id_str(i))
        missing = _scene_missing(folder, cfg) if folder.is_dir() else None
        if missing is not None:
            raise GenerateError(f"{out / missing}: missing, so {folder} is not a complete scene; remove that folder "
                                "(it is regenerated) or use --overwrite")
    for stale in (out / VIDEOS_DIR).glob(".*.partial"):  # left by an interrupted scene
        shutil.rmtree(stale)


_worker_library: list | None = None


def _generate_in_worker(cfg_dict: dict, index: int, final_dir: str, cache_dir: str, pinned: bool) -> dict:
    """Executor entry: load the library once per worker process, then generate one scene. A scene already in
    place was finished by an attempt whose worker died before replying (Ray re-runs such tasks): no timings.
    ``pinned``: whether the command runs pinned (:mod:`selfseg.generate.determinism`); a worker that started
    otherwise would compute other bytes, so it refuses (GenerateError)."""
    global _worker_library
    if is_pinned(start_environ()) != pinned:
        raise GenerateError(f"a worker on {socket.gethostname()} (pid {os.getpid()}) started with its numerical "
                            f"libraries {'not ' if pinned else ''}pinned, unlike this command: its scenes would "
                            "differ from this machine's (see selfseg.generate.determinism)")
    if Path(final_dir).is_dir():
        return {}
    cfg = from_dict(GenerateConfig, cfg_dict)
    if _worker_library is None:
        _worker_library = load_library(cfg)
    return generate_scene(cfg, index, _worker_library, Path(final_dir), Path(cache_dir), progress=False)


def _summary(totals: dict, wall: float, n_frames: int, n_done: int, n_skipped: int, out: Path) -> str:
    lines = [f"generate_scenes: {out}: {n_done} scenes generated, {n_skipped} already complete, "
             f"{n_frames} frames rendered in {wall:.1f} s"]
    lines.append(f"  {'stage':<14}{'seconds':>10}{'s/frame':>10}")
    for stage, sec in totals.items():
        per = f"{sec / n_frames:10.3f}" if n_frames and stage not in ("validate", "models") else f"{'':>10}"
        lines.append(f"  {stage:<14}{sec:10.2f}{per}")
    return "\n".join(lines)


def open_executor(args: argparse.Namespace) -> cf.Executor | None:
    """The scene executor: None for local rendering in this process (``--workers 1``), a spawn process pool for
    local workers, or Ray tasks (starts or joins Ray; raises ExecutorError for bad executor options)."""
    if args.workers < 1:
        raise GenerateError(f"--workers must be at least 1, got {args.workers}")
    if args.executor == "local" and args.ray_address is None and args.workers == 1:
        return None
    where = executor_config(args, None)
    env = start_environ()  # Ray workers, on any node, start pinned as this command is (a local pool inherits it)
    return make_executor(where.kind, where.ray_address, args.workers, num_cpus=where.ray_cpus_per_task,
                         num_gpus=where.ray_gpus_per_task, env_vars=pinned_vars(env) if is_pinned(env) else None,
                         mp_context=multiprocessing.get_context("spawn"))  # bpy is not fork-safe


def _existing_ancestor(path: Path) -> Path:
    """``path`` if it is a folder, else its nearest existing parent (where the shared-folder probe can go)."""
    path = path.resolve()
    while not path.is_dir():
        path = path.parent
    return path


def validate(args: argparse.Namespace, executor: cf.Executor | None = None) -> tuple[GenerateConfig, list]:
    """Resolve the config, load the object library, check that Ray workers (if any) see the output folder and
    check the output folder (raises on bad input, before anything is written)."""
    cfg = config_from_args(args)
    if not 0 <= cfg.seed < 2**32:
        raise GenerateError(f"--seed must be an integer in [0, 2^32), got {cfg.seed}")
    step = orbit_step_deg(cfg.orbit, cfg.frames) * cfg.frame_step
    if step > 2.0:
        print(f"generate_scenes: warning: the camera turns {step:.1f}° between rendered frames; "
              "frame-to-frame tracking needs about 2° at most (lower --frame-step)", file=sys.stderr)
    library = load_library(cfg)
    if args.executor == "ray":
        check_shared_folder(executor, _existing_ancestor(args.out))
    prepare_output(args.out, cfg, args.overwrite)
    return cfg, library


def run(args: argparse.Namespace, cfg: GenerateConfig, library: list, t_start: float,
        executor: cf.Executor | None = None) -> int:
    """Generate the missing scenes (on ``executor``, else in this process), then the models and
    dataset_info.json; print the timing summary."""
    totals = {"validate": time.perf_counter() - t_start, **dict.fromkeys(STAGES, 0.0), "models": 0.0}
    out: Path = args.out
    out.mkdir(parents=True, exist_ok=True)
    cfg_dict = recorded_config(cfg)
    write_json(out / PROGRESS_FILE, {"config": cfg_dict, "generator_version": GENERATOR_VERSION})
    cache_dir = args.cache_dir / "physics"
    todo = [i for i in range(cfg.scenes) if not (out / VIDEO_DIR.format(video_id=video_id_str(i))).is_dir()]
    skipped = cfg.scenes - len(todo)
    bar = tqdm(total=cfg.scenes, initial=skipped, desc="scenes", unit="scene", disable=args.quiet)
    if executor is None or (args.executor == "local" and len(todo) <= 1):
        for i in todo:
            t = generate_scene(cfg, i, library, out / VIDEO_DIR.format(video_id=video_id_str(i)), cache_dir,
                               progress=not args.quiet)
            for k, v in t.items():
                totals[k] += v
            bar.update()
    else:
        futures = [executor.submit(_generate_in_worker, cfg_dict, i,
                                   str(out / VIDEO_DIR.format(video_id=video_id_str(i))), str(cache_dir),
                                   is_pinned(start_environ())) for i in todo]
        for fut in cf.as_completed(futures):
            for k, v in fut.result().items():
                totals[k] += v
            bar.update()
        for stale in (out / VIDEOS_DIR).glob(".*.partial"):  # left by a worker that died mid-scene (re-run since)
            shutil.rmtree(stale)
    bar.close()

    t0 = time.perf_counter()
    write_models(out, library)
    write_dataset_info(out, {
        "name": cfg.preset, "generator_version": GENERATOR_VERSION, "resolution": [cfg.width, cfg.height],
        "config": cfg_dict, "seed": cfg.seed, "frame_ids": cfg.frame_ids,
        "objects": [{"obj_id": i + 1, "name": o.name, "source": o.source, "nonconvex": bool(o.nonconvex)}
                    for i, o in enumerate(library)]})
    digest = write_manifest(out)
    geometry = geometry_hash(read_manifest(out)["files"])
    (out / PROGRESS_FILE).unlink()
    totals["models"] = time.perf_counter() - t0
    print(_summary(totals, time.perf_counter() - t_start, len(todo) * len(cfg.frame_ids), len(todo), skipped, out))
    print(f"generate_scenes: {out}: manifest hash {digest} (geometry hash {geometry}: every file but the RGB frames)")
    return 0


def main(argv: list[str] | None = None) -> int:
    if argv is None:  # the command: the same bytes on every x86-64 machine (selfseg.generate.determinism)
        reexec_pinned("selfseg.generate.cli")
    args = build_parser().parse_args(argv)
    if args.verify is not None:
        return verify_dataset(args.verify)
    if args.out is None:
        build_parser().error("--out is required (or --verify DIR)")
    t_start = time.perf_counter()
    try:
        executor = open_executor(args)
    except (GenerateError, ExecutorError) as e:
        print(f"generate_scenes: error: {e}", file=sys.stderr)
        return EXIT_BAD_INPUT
    try:
        with executor if executor is not None else contextlib.nullcontext():
            try:
                cfg, library = validate(args, executor)
            except (GenerateError, ConfigError, DatasetError, FileFormatError, ValueError) as e:  # incl. ExecutorError
                print(f"generate_scenes: error: {e}", file=sys.stderr)
                return EXIT_BAD_INPUT
            try:
                return run(args, cfg, library, t_start, executor)
            except GenerateError as e:  # a worker that would compute other bytes
                print(f"generate_scenes: error: {e}", file=sys.stderr)
                return EXIT_BAD_INPUT
    except KeyboardInterrupt:
        print("generate_scenes: interrupted; completed scenes are kept, re-run the same command to resume",
              file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
