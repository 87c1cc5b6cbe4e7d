"""Training data of the Table I baselines trained on synthetic scenes of *other* objects
(``uois-sim``, ``sdmaskrcnn-sim``): the disjoint-pool dataset, its checks and its frames.

The training dataset is a separate folder (``train_data``), generated with ``generate_scenes
--object-pool`` so that it holds none of the test dataset's objects. Its ground truth is read
freely: the evaluator's guard only covers the *test* dataset's folder. A missing dataset or one
sharing an object name with the test dataset raises :class:`selfseg.dataset.DatasetError`
(``evaluate`` prints it as one line, exit 2).
"""
from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path
from typing import ClassVar

import numpy as np

from selfseg.baselines.semantic_instances import result_key
from selfseg.dataset import Dataset, DatasetError, Video
from selfseg.fileio import hash_json
from selfseg.method.train import OptimSchedule
from selfseg.method_api import Method
from selfseg.raycast import xyz_map

SHARED_TRAIN_DIR = "{method}-{key_hash:.12}"  # beside the fold folders: a method's networks trained on train_data


@dataclass
class SimSchedule(OptimSchedule):
    """Optimisation of one supervised training phase (steps of ``batch_size`` full training frames,
    randomly flipped)."""

    steps: int = 2000
    batch_size: int = 4


def object_names(ds: Dataset) -> set[str]:
    """Names of the objects a dataset draws from (``dataset_info.json`` → ``objects``)."""
    return {str(o["name"]) for o in ds.info.get("objects", [])}


def open_disjoint_train_data(path: str, test_root: Path, method: str) -> Dataset:
    """The training dataset at ``path``, checked to exist and to share no object with the test dataset
    (``test_root``: the folder of the videos ``fit`` was given, which holds the test dataset's info)."""
    if not path:
        raise DatasetError(f"{method} needs train_data: a dataset generated with an object pool disjoint from the "
                           f"test data (generate_scenes --object-pool ...), given with --set train_data=PATH")
    # absolute: a method's sandbox refuses ground-truth names on relative paths (it cannot tell them from
    # opens relative to a directory descriptor)
    try:
        train = Dataset(os.path.abspath(path))
    except DatasetError as e:
        raise DatasetError(f"{method} train_data is not usable: {e}") from None
    test = Dataset(test_root)
    if train.root.resolve() == test.root.resolve() or train.info == test.info:  # (the evaluator may give a copy)
        raise DatasetError(f"{method} train_data {path} is the test dataset itself; give a disjoint-object dataset")
    shared = sorted(object_names(train) & object_names(test))
    if shared:
        raise DatasetError(f"{method} train_data {path} shares objects with the test dataset {test.root}: "
                           f"{', '.join(shared)}; generate it with a disjoint --object-pool")
    return train


def train_data_record(ds: Dataset) -> dict:
    """What a run's provenance records of its training dataset."""
    return {"name": ds.name, "root": str(ds.root.resolve()), "content_hash": ds.content_hash(),
            "n_videos": len(ds.video_ids), "objects": sorted(object_names(ds))}


class GTFrames:
    """Every ``frame_stride``-th frame of every video of a labelled dataset: (rgb uint8 H×W×3,
    depth float32 H×W m, xyz float32 H×W×3 m, inst int32 H×W), read once and kept in memory."""

    def __init__(self, ds: Dataset, frame_stride: int):
        self.items = [(ds.labeled(v), f) for v in ds.video_ids for f in ds.labeled(v).frame_ids[::frame_stride]]
        self._cache: dict[int, tuple[np.ndarray, ...]] = {}

    def __len__(self) -> int:
        return len(self.items)

    def __getitem__(self, i: int) -> tuple[np.ndarray, ...]:
        if i not in self._cache:
            video, f = self.items[i]
            depth = video.depth_m(f)
            self._cache[i] = (video.rgb(f), depth, xyz_map(depth, video.K(f)), video.inst(f).astype(np.int32))
        return self._cache[i]

    def batch(self, seed: int, step: int, batch_size: int) -> list[tuple[np.ndarray, ...]]:
        """The frames of training step ``step``, a pure function of (seed, step), each flipped
        left-right with probability ½ (xyz's x negated with it, so the map stays a camera-frame one)."""
        rng = np.random.default_rng([seed, step])
        idx = rng.choice(len(self), batch_size, replace=len(self) < batch_size)
        out = []
        for i in idx:
            rgb, depth, xyz, inst = self[int(i)]
            if rng.random() < 0.5:
                xyz = xyz[:, ::-1] * np.array([-1, 1, 1], np.float32)
                rgb, depth, inst = rgb[:, ::-1], depth[:, ::-1], inst[:, ::-1]
            out.append(tuple(np.ascontiguousarray(a) for a in (rgb, depth, xyz, inst)))
        return out


def shared_train_dir(workdir: Path | None, method: str, key: dict) -> Path:
    """Where a method trained only on ``train_data`` keeps its networks: beside the fold folders
    (``work/<run>/<dataset>/<method>-<key hash>``), so the three folds train once; the hash keeps
    other settings apart."""
    fold_dir = Path(workdir) if workdir is not None else Path("work/fold")
    return fold_dir.parent / SHARED_TRAIN_DIR.format(method=method, key_hash=hash_json(key))


class SimTrainedMethod(Method):
    """A baseline trained only on ``config.train_data``; ``test_time_fields`` are the config's settings
    read at test time alone (changing them reuses the trained networks)."""

    needs_ground_truth = False  # the *test* dataset's labels are never read; train_data is another dataset
    needs_fit = True
    test_time_fields: ClassVar[tuple[str, ...]] = ()

    def __init__(self, config=None, workdir: str | Path | None = None):
        super().__init__(config, workdir)
        self.train_data: dict | None = None  # provenance of the training dataset (set by fit)

    def open_training(self, train_videos: list[Video]) -> tuple[Dataset, dict, Path]:
        """The checked training dataset (recorded in ``train_data``), the training key (the config less its
        test-time settings, the data's content hash) and the shared training folder."""
        ds = open_disjoint_train_data(self.config.train_data, train_videos[0].root, self.name)
        self.train_data = train_data_record(ds)
        config = {k: v for k, v in result_key(self.config).items() if k not in self.test_time_fields + ("train_data",)}
        key = {"config": config, "train_data": self.train_data["content_hash"]}
        return ds, key, shared_train_dir(self.workdir, self.name, key)
