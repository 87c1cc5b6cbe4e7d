"""The self-supervised pipeline of Lu et al. (`ours`) and its Table III ablations, as stages exchanging files.

Per video, shared by every fold and variant (``STAGES/<stage>/<video_id>/``, see
:class:`selfseg.stages.StageCache`; a re-run reuses every stage whose key still matches):

- ``recon``: camera tracking, TSDF fusion and support-plane removal (:mod:`selfseg.method.recon_stage`);
- ``overseg``: LCCP + SymSeg over-segmentation of the object points, the segment graph
  (``segments.npz``) and the segments projected into every frame (``segmaps/{fid:06d}.png``).

Per set of training videos, also in the shared stage cache:

- ``phi1/<hash>/``: φ1, trained on the over-segment maps (the hash covers its settings and data), and the φ1
  segment features of its training videos (``features-<hash>/<vid>.npy``), shared by `ours` and the
  ablations that match with the same φ1.
- ``matches/matches-<hash>.json``: the matching of those segment graphs under one MatchConfig (the hash covers
  both), so that `ours` and V3, which differ only after it, match once; run side by side, one waits for the
  other's solve (``.matches-<hash>.lock``).

Per fold, in the method's workdir (keyed by the settings and the training videos):

- ``pseudo/all/scenes/``: φ1 segment features (``features/<vid>.npy``), cross-scene matching
  (``matches.json``), per-point object pseudo-labels (``labels/<vid>.npy``) and their projection into
  the frames (``maps/<vid>/{fid:06d}.png``);
- ``net-<hash>/``: φ2, trained on the pseudo-label maps (:class:`EmbeddingMethodBase`).

Label maps on disk are uint16 PNGs: 0 = no label, s + 1 = segment or object s. In memory they are
int32 with −1 = no label. Everything here reads only unlabeled :class:`~selfseg.dataset.Video`
objects: ground-truth camera poses are used only with ``recon.use_gt_poses`` (an ablation).
"""
from __future__ import annotations

import concurrent.futures as cf
import io
import os
import time
from dataclasses import dataclass, field, replace
from itertools import repeat
from pathlib import Path
from typing import Literal

import numpy as np
from tqdm import tqdm

from selfseg.config import to_dict
from selfseg.dataset import Video, read_inst
from selfseg.fileio import atomic_write_bytes, hash_json, read_json, write_json
from selfseg.guard import ground_truth_forbidden
from selfseg.method.background import BackgroundConfig
from selfseg.method.embed_method import EmbeddingMethodBase, EmbeddingMethodConfig, video_key
from selfseg.method.overseg import OversegConfig, oversegment
from selfseg.method.projection import project_labels
from selfseg.method.pseudolabels import DIAGNOSTICS_JSON, PseudoLabelConfig, SceneData, make_pseudo_labels
from selfseg.method.recon_stage import ReconStage, load_recon, run_recon_stage
from selfseg.method.reconstruct import ReconConfig
from selfseg.method.segment_graph import SegmentGraph, build_segment_graph
from selfseg.method.train import FrameLabelSource, TrainConfig, load_embedding_net, train_embedding
from selfseg.stages import STAGE_FILE, StageCache
from selfseg.writers import write_inst

# Files of the stages this module owns (recon's are in selfseg.method.recon_stage), relative to the stage folder.
SEGMENTS_NPZ = "segments.npz"  # overseg: the segment graph (segment per reconstructed point, −1 = none; edges; sizes)
SEGMAPS_DIR = "segmaps"  # overseg: the segments projected into every frame (LABEL_MAP_PNG files)
OVERSEG_REPORT_JSON = "report.json"  # overseg: point, segment, edge and component counts; timings (s)
MATCH_CACHE_DIR = "matches"  # in the stage root: matchings kept for runs that share them (pseudolabels.MATCH_CACHE_JSON)
PHI1_DIR = "phi1/{key_hash}"  # in the stage root: φ1 trained on the over-segments of a set of videos
PHI1_FEATURES_NPY = "features-{key_hash}/{video_id}.npy"  # in a PHI1_DIR: φ1 feature per segment of a training
# video (n_segments × D, unit vectors); the hash covers the feature settings and the device
FEATURES_NPY = "features/{video_id}.npy"  # pseudo: φ1 feature per segment (n_segments × D, unit vectors)
LABELS_NPY = "labels/{video_id}.npy"  # pseudo: object pseudo-label per reconstructed point (−1 = none)
PSEUDO_MAPS_DIR = "maps/{video_id}"  # pseudo: the pseudo-labels projected into every frame (LABEL_MAP_PNG files)
PSEUDO_CACHE_DIR = "pseudo"  # in the method's workdir: the pseudo stage (one per set of training videos)
PSEUDO_STAGE = ("all", "scenes")  # (stage, scene) of the pseudo stage in its cache: PSEUDO_CACHE_DIR/all/scenes
LABEL_MAP_PNG = "{frame_id:06d}.png"  # one frame's label map in SEGMAPS_DIR or PSEUDO_MAPS_DIR (uint16, 0 = none)
ROWS_3D = ("lccp", "lccp+symseg", "ours-matching")  # the 3-D segmentations :meth:`Ours.segment_3d` gives (Table II)

STAGE_VERSION = 3  # bump when a stage's output format or algorithm changes (2: cloud-anchored supervoxel grids; 3: diagnostics.json)


@dataclass
class ProjectionConfig:
    """Projection of labelled 3D points into frames (z-buffer with a depth test against the frame's depth)."""

    splat_px: int = 1  # half-size of each point's square splat, pixels
    depth_tol_m: float = 0.01


@dataclass
class OursConfig(EmbeddingMethodConfig):
    """Every setting of the pipeline; ``net``, ``train``, ``cluster``, ``frame_stride`` and ``device`` are φ2's."""

    recon: ReconConfig = field(default_factory=ReconConfig)
    background: BackgroundConfig = field(default_factory=BackgroundConfig)
    overseg: OversegConfig = field(default_factory=OversegConfig)
    adjacency_radius_m: float = 0.0075  # segments whose points come this close share a graph edge
    projection: ProjectionConfig = field(default_factory=ProjectionConfig)
    phi1_train: TrainConfig = field(default_factory=TrainConfig)
    feature_stride: int = 5  # φ1 segment features average every n-th frame
    pseudo: PseudoLabelConfig = field(default_factory=PseudoLabelConfig)
    labels: Literal["pseudo", "overseg"] = "pseudo"  # "overseg": V2, φ2 = φ1 trained on LCCP labels
    stage_dir: str = ""  # per-video stage cache; "" = <stage root>/<dataset folder>-<path hash> (see stage_cache)


@dataclass
class OursV2Config(OursConfig):
    labels: Literal["pseudo", "overseg"] = "overseg"


@dataclass
class OursV3Config(OursConfig):
    pseudo: PseudoLabelConfig = field(default_factory=lambda: PseudoLabelConfig(mode="v3_no_pruning"))


@dataclass
class OursV4Config(OursConfig):
    pseudo: PseudoLabelConfig = field(default_factory=lambda: PseudoLabelConfig(mode="v4_registration_only"))


@dataclass
class Segmentation3D:
    """One video's reconstruction (object points in its world frame, metres) and the per-point labels of
    each requested Table II row (−1 = none), with its segment graph and φ1 segment features (``features``:
    n_segments × D, only with the ``ours-matching`` row)."""

    video_id: str
    recon: ReconStage
    labels: dict[str, np.ndarray]
    graph: SegmentGraph
    features: np.ndarray | None = None


@dataclass
class Segmentations3D:
    """:meth:`Ours.segment_3d`'s answer: every video's segmentations, the matching step's diagnostics
    (``ours-matching`` only) and the seconds each step took in this call (cached stages cost ~0)."""

    scenes: list[Segmentation3D]
    diagnostics: dict | None
    seconds: dict[str, float]


def lccp_only(config: OursConfig) -> OursConfig:
    """The config of the ``lccp`` row: the pipeline's, with SymSeg off."""
    return replace(config, overseg=replace(config.overseg, use_symseg=False))


def read_label_map(path: str | Path) -> np.ndarray:
    """uint16 label PNG (0 = none, s + 1 = label s) → int32 map with −1 = none."""
    return read_inst(path).astype(np.int32) - 1


def write_label_maps(out_dir: Path, video: Video, points_w: np.ndarray, labels: np.ndarray,
                     T_world_cam: dict[int, np.ndarray], cfg: ProjectionConfig, progress: bool = True) -> None:
    """Project labelled points (world m; labels ≥ 0, −1 skipped) into every frame with a pose."""
    keep = labels >= 0
    pts, lab = points_w[keep], labels[keep]
    for fid in tqdm(video.frame_ids, desc=f"video {video.video_id}: project labels", unit="frame",
                    disable=not progress, leave=False):
        if fid not in T_world_cam:
            continue
        m = project_labels(pts, lab, video.K(fid), T_world_cam[fid], video.width, video.height,
                           depth_m=video.depth_m(fid), depth_tol_m=cfg.depth_tol_m, splat_px=cfg.splat_px)
        write_inst(out_dir / LABEL_MAP_PNG.format(frame_id=fid), (m + 1).astype(np.uint16))


def run_overseg_stage(video: Video, cache: StageCache, cfg: OursConfig, progress: bool = True) -> Path:
    """Reconstruct (cached) and over-segment one video; returns the stage folder."""
    recon_dir = run_recon_stage(video, cache, cfg.recon, cfg.background)
    key = {"version": STAGE_VERSION, "video": video_key(video), "recon": cache.key_hash("recon", video.video_id),
           "overseg": to_dict(cfg.overseg), "adjacency_radius_m": cfg.adjacency_radius_m,
           "projection": to_dict(cfg.projection)}
    if cache.is_valid("overseg", video.video_id, key):
        return cache.path("overseg", video.video_id)
    rec = load_recon(recon_dir)
    t0 = time.perf_counter()
    # VCCS colour distances use 0–255 like PCL; reconstructed colours are in [0, 1]
    labels = oversegment(rec.points_w, rec.normals_w, rec.colors * 255.0, rec.occupancy, cfg.overseg)
    t1 = time.perf_counter()
    graph = build_segment_graph(rec.points_w, labels, cfg.adjacency_radius_m)
    t2 = time.perf_counter()
    with cache.write("overseg", video.video_id, key) as tmp:
        graph.save(tmp / SEGMENTS_NPZ)
        write_label_maps(tmp / SEGMAPS_DIR, video, rec.points_w, labels, rec.T_world_cam, cfg.projection, progress)
        write_json(tmp / OVERSEG_REPORT_JSON, {
            "n_points": len(labels), "n_segments": graph.n_segments, "n_edges": len(graph.edges),
            "n_components": len(graph.components()),
            "timings_s": {"overseg_s": round(t1 - t0, 3), "graph_s": round(t2 - t1, 3),
                        "maps_s": round(time.perf_counter() - t2, 3)}})
    return cache.path("overseg", video.video_id)


def overseg_task(video: Video, cache: StageCache, cfg: OursConfig) -> Path:
    """:func:`run_overseg_stage` as one executor task (another process or node): quiet, with the video's
    dataset guarded there too (the self-supervised path never reads ground truth)."""
    with ground_truth_forbidden(video.root):
        return run_overseg_stage(video, cache, cfg, progress=False)


def _map_loader(folder_of: dict[str, Path]):
    """Label loader for :class:`FrameLabelSource`: reads ``folder_of[video_id]/{fid:06d}.png``."""
    def load(video: Video, fid: int) -> np.ndarray:
        return read_label_map(folder_of[video.video_id] / LABEL_MAP_PNG.format(frame_id=fid))
    return load


def _fg_loader(cache: StageCache):
    """Foreground loader for :class:`FrameLabelSource`: the recon stage's projected foreground mask of the
    frame (the method's own, never ground truth), for ``TrainConfig.mask_background``."""
    recons: dict[str, ReconStage] = {}

    def load(video: Video, fid: int) -> np.ndarray:
        if video.video_id not in recons:
            recons[video.video_id] = load_recon(cache.path("recon", video.video_id))
        return recons[video.video_id].fg_mask(fid)
    return load


class Ours(EmbeddingMethodBase):
    """The paper's method: φ1 on over-segments → graph matching → pseudo-labels → φ2 + mean-shift."""

    name = "ours"
    config_cls = OursConfig
    # where per-video stages, matching and registrations fan out (evaluate3d --executor ray); None: the
    # per-video stages one after the other in this process, matching and registrations in a local process pool
    executor: cf.Executor | None = None

    def stage_cache(self, videos: list[Video]) -> StageCache:
        """The per-video stage cache of ``videos``' dataset: ``config.stage_dir`` if set, else
        ``<stage root>/<dataset folder>-<path hash>`` (stage root: :attr:`stage_root`, which the harness passes
        in, else ``workdir/_stages``). Stage keys hold the dataset's path, so the method's unlabeled view and
        evaluate3d's real dataset (same folder name) get separate caches instead of rebuilding each other's."""
        if self.config.stage_dir:
            return StageCache(self.config.stage_dir)
        if self.stage_root is None and self.workdir is None:
            raise ValueError(f"method {self.name!r} needs a stage root, a workdir or config stage_dir for its stages")
        base = self.stage_root if self.stage_root is not None else self.workdir / "_stages"
        root = videos[0].root
        return StageCache(Path(base) / f"{root.name}-{hash_json(os.path.abspath(root), n=8)}")

    def run_overseg(self, videos: list[Video]) -> StageCache:
        """Reconstruct and over-segment every video (per-video stages, cached); returns the stage cache."""
        cache = self.stage_cache(videos)
        desc = f"{self.name}: reconstruct + over-segment"
        if self.executor is None:
            for v in tqdm(videos, desc=desc, unit="video"):
                run_overseg_stage(v, cache, self.config)
        else:  # one task per video; each writes its own stage folders (atomically, the first writer wins)
            for _ in tqdm(self.executor.map(overseg_task, videos, repeat(cache), repeat(self.config)), desc=desc,
                          unit="video", total=len(videos)):
                pass
        return cache

    def train_phi1(self, videos: list[Video], cache: StageCache) -> Path:
        """Train φ1 on the over-segment maps of ``videos`` (cached by settings and stage keys); returns its weights."""
        segmaps = {v.video_id: cache.path("overseg", v.video_id) / SEGMAPS_DIR for v in videos}
        source = FrameLabelSource([(v, f, _map_loader(segmaps)) for v in videos for f in self.training_frames(v)],
                                  foreground=_fg_loader(cache), geometry=self.config.net.geometry)
        key = {"phi1": to_dict(self.config.phi1_train), "net": to_dict(self.config.net),
               "frame_stride": self.config.frame_stride,
               "overseg": [cache.key_hash("overseg", v.video_id) for v in videos]}
        # shared by folds and variants with the same training videos and settings
        return train_embedding(source, self.config.phi1_train, self.config.net,
                               cache.root / PHI1_DIR.format(key_hash=hash_json(key)))

    def pseudo_labels(self, videos: list[Video], cache: StageCache, phi1: Path) -> Path:
        """φ1 segment features, cross-scene matching and merged pseudo-labels of the training videos (cached)."""
        cfg = self.config
        out = StageCache(self.workdir / PSEUDO_CACHE_DIR)
        key = {"version": STAGE_VERSION, "phi1": str(phi1), "pseudo": to_dict(cfg.pseudo),
               "feature_stride": cfg.feature_stride, "projection": to_dict(cfg.projection),
               "overseg": [cache.key_hash("overseg", v.video_id) for v in videos]}
        if out.is_valid(*PSEUDO_STAGE, key):
            return self.pseudo_dir()
        scenes, recons = [], []
        for v in tqdm(videos, desc="φ1 segment features", unit="video"):
            graph = SegmentGraph.load(cache.path("overseg", v.video_id) / SEGMENTS_NPZ)
            recons.append(load_recon(cache.path("recon", v.video_id)))
            feats = self.phi1_features(v, graph, recons[-1], cache, phi1)
            scenes.append(SceneData(v.video_id, recons[-1].points_w, graph, feats))
        with out.write(*PSEUDO_STAGE, key) as tmp:
            labels = make_pseudo_labels(scenes, cfg.pseudo, tmp, executor=self.executor,
                                        match_cache=cache.root / MATCH_CACHE_DIR)
            for v, scene, rec in zip(videos, scenes, recons):
                for template, array in ((FEATURES_NPY, scene.features), (LABELS_NPY, labels[v.video_id])):
                    (tmp / template.format(video_id=v.video_id)).parent.mkdir(exist_ok=True)
                    np.save(tmp / template.format(video_id=v.video_id), array)
                write_label_maps(tmp / PSEUDO_MAPS_DIR.format(video_id=v.video_id), v, scene.points_w,
                                 labels[v.video_id], rec.T_world_cam, cfg.projection)
        return self.pseudo_dir()

    def phi1_features(self, video: Video, graph: SegmentGraph, recon: ReconStage, cache: StageCache,
                      phi1: Path) -> np.ndarray:
        """φ1 feature per segment of ``video`` (n_segments × D, unit vectors), read from the φ1 folder when another
        method has already computed it with this φ1 (PHI1_FEATURES_NPY), else computed and written there."""
        from selfseg.method.features import segment_features

        cfg = self.config
        # φ1's folder hash covers its training videos' over-segmentation; this hash the features' own settings
        key = {"feature_stride": cfg.feature_stride, "image_size": cfg.phi1_train.image_size,
               "crop_margin": cfg.phi1_train.crop_margin, "mask": cfg.phi1_train.mask_background,
               "device": self._device.type}
        path = phi1.parent / PHI1_FEATURES_NPY.format(key_hash=hash_json(key), video_id=video.video_id)
        if path.is_file():
            return np.load(path)
        seg_dir = cache.path("overseg", video.video_id)
        frames = video.frame_ids[::cfg.feature_stride]
        segmaps = {f: read_label_map(seg_dir / SEGMAPS_DIR / LABEL_MAP_PNG.format(frame_id=f)) for f in frames}
        fgs = {f: recon.fg_mask(f) for f in frames} if cfg.phi1_train.mask_background else None
        net = load_embedding_net(phi1, self._device)
        feats, _seen = segment_features(net, video, frames, segmaps, graph.n_segments, self._device,
                                        image_size=cfg.phi1_train.image_size,  # φ1 at its training scale
                                        fg_crop_margin=cfg.phi1_train.crop_margin, fg_masks=fgs)
        buf = io.BytesIO()
        np.save(buf, feats)
        atomic_write_bytes(path, buf.getvalue())
        return feats

    def pseudo_dir(self) -> Path:
        """The folder of the pseudo stage in the workdir (features, matches.json, diagnostics.json, labels, maps)."""
        return StageCache(self.workdir / PSEUDO_CACHE_DIR).path(*PSEUDO_STAGE)

    def label_source(self, train_videos: list[Video]):
        cache = self.run_overseg(train_videos)
        pseudo = self.pseudo_labels(train_videos, cache, self.train_phi1(train_videos, cache))
        folders = {v.video_id: pseudo / PSEUDO_MAPS_DIR.format(video_id=v.video_id) for v in train_videos}
        source = FrameLabelSource([(v, f, _map_loader(folders)) for v in train_videos for f in self.training_frames(v)],
                                  foreground=_fg_loader(cache), geometry=self.config.net.geometry)
        return source, {"pseudo": read_json(pseudo / STAGE_FILE)["key_hash"]}

    def segment_3d(self, videos: list[Video], rows: tuple[str, ...] = ROWS_3D) -> Segmentations3D:
        """The 3-D segmentations of ``videos`` (one unlabeled collection: φ1 and matching run over all of
        them) that Table II scores, per video: the reconstruction and the per-point labels of each row in
        ``rows`` (``lccp``: LCCP alone, re-run in memory on the cached reconstruction; ``lccp+symseg``: the
        over-segmentation stage; ``ours-matching``: the object pseudo-labels after matching and pruning)."""
        bad = [r for r in rows if r not in ROWS_3D]
        if bad or not rows:
            raise ValueError(f"rows: unknown row(s) {bad or list(rows)}; choose from {', '.join(ROWS_3D)}")
        seconds: dict[str, float] = {}
        t0 = time.perf_counter()
        cache = self.run_overseg(videos)
        seconds["recon_overseg_s"] = time.perf_counter() - t0
        scenes = []
        for v in videos:
            graph = SegmentGraph.load(cache.path("overseg", v.video_id) / SEGMENTS_NPZ)
            scenes.append(Segmentation3D(v.video_id, load_recon(cache.path("recon", v.video_id)), {}, graph))
            if "lccp+symseg" in rows:
                scenes[-1].labels["lccp+symseg"] = graph.labels
        if "lccp" in rows:
            t0 = time.perf_counter()
            cfg = lccp_only(self.config).overseg
            for s in tqdm(scenes, desc="LCCP without SymSeg", unit="video"):
                # VCCS colour distances use 0–255 like PCL (as in the overseg stage)
                s.labels["lccp"] = oversegment(s.recon.points_w, s.recon.normals_w, s.recon.colors * 255.0,
                                               s.recon.occupancy, cfg)
            seconds["lccp_s"] = time.perf_counter() - t0
        diagnostics = None
        if "ours-matching" in rows:
            t0 = time.perf_counter()
            phi1 = self.train_phi1(videos, cache)
            seconds["phi1_s"] = time.perf_counter() - t0
            t0 = time.perf_counter()
            pseudo = self.pseudo_labels(videos, cache, phi1)
            seconds["pseudo_s"] = time.perf_counter() - t0
            for s in scenes:
                s.labels["ours-matching"] = np.load(pseudo / LABELS_NPY.format(video_id=s.video_id))
                s.features = np.load(pseudo / FEATURES_NPY.format(video_id=s.video_id))
            diagnostics = read_json(pseudo / DIAGNOSTICS_JSON)
        return Segmentations3D(scenes, diagnostics, seconds)

    def network_train_config(self) -> TrainConfig:
        return self.config.phi1_train if self.config.labels == "overseg" else self.config.train

    def fit(self, train_videos: list[Video]) -> None:
        if self.workdir is None:
            raise ValueError(f"method {self.name!r} needs a workdir to store its stages and networks")
        if self.config.labels == "overseg":  # V2: the network trained on over-segments is the final one
            self.load(self.train_phi1(train_videos, self.run_overseg(train_videos)))
        else:
            super().fit(train_videos)


class OursV2(Ours):
    """Table III V2: φ2 trained on the LCCP + SymSeg over-segments, no graph matching."""

    name = "ours-v2"
    config_cls = OursV2Config


class OursV3(Ours):
    """Table III V3: graph matching without pruning."""

    name = "ours-v3"
    config_cls = OursV3Config


class OursV4(Ours):
    """Table III V4: exhaustive registration instead of graph matching."""

    name = "ours-v4"
    config_cls = OursV4Config
