"""The clustering's torch path (any device, several frames in one batch) against the numpy path.

Criterion: on the CPU the torch path gives labels identical to the numpy path's; on CUDA, whose float rounding
differs, every instance of the numpy result is matched (Hungarian) to one of the torch result with IoU ≥ .999,
and the number of instances is the same. Frames are the analytic dataset's ground-truth instance maps (real
foreground masks, 160×120, 2–3 objects) with one random unit direction per object plus per-pixel noise.
"""
import numpy as np
import pytest
import torch
from scipy.optimize import linear_sum_assignment
from test_meanshift import assert_same_partition, clusters, unit

from selfseg.config import to_dict
from selfseg.dataset import Dataset
from selfseg.method.embed_method import EmbeddingMethodConfig
from selfseg.method.meanshift import MeanShiftConfig, _cluster, cluster_frame, cluster_frames, vmf_meanshift
from selfseg.method.network import EmbeddingNet, NetConfig
from selfseg.registry import get_method_class

DEVICES = ["cpu", pytest.param("cuda", marks=pytest.mark.skipif(not torch.cuda.is_available(), reason="no GPU"))]


@pytest.fixture(autouse=True)
def one_cpu_thread():
    """torch at one CPU thread: on a loaded 2-core machine, two threads made these small ops 30× slower."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


@pytest.fixture(scope="module")
def frames(analytic_dataset) -> list[np.ndarray]:
    """Ground-truth instance maps of every analytic frame (0 = background)."""
    ds = Dataset(analytic_dataset)
    return [v.inst(f).astype(np.int64) for v in map(ds.labeled, ds.video_ids) for f in v.frame_ids]


def object_embeddings(inst: np.ndarray, noise: float, seed: int, dim: int = 16) -> np.ndarray:
    """float32 D×H×W unit embeddings: a random unit direction per instance plus Gaussian noise (σ per dimension)."""
    rng = np.random.default_rng(seed)
    centers = unit(rng.normal(size=(inst.max() + 1, dim)))
    return unit(centers[inst] + noise * rng.normal(size=inst.shape + (dim,))).astype(np.float32).transpose(2, 0, 1)


def matched_ious(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """IoU of each instance of map ``a`` with the instance of ``b`` matched to it (Hungarian; 0 if unmatched)."""
    ids_a, ids_b = np.unique(a[a > 0]), np.unique(b[b > 0])
    iou = np.array([[((a == i) & (b == j)).sum() / ((a == i) | (b == j)).sum() for j in ids_b] for i in ids_a])
    out = np.zeros(len(ids_a))
    if len(ids_b):
        rows, cols = linear_sum_assignment(-iou)
        out[rows] = iou[rows, cols]
    return out


def assert_same_instances(ref: np.ndarray, got: np.ndarray, device: str) -> None:
    """The module's criterion: identical on the CPU; same count and every IoU ≥ .999 on CUDA."""
    if device == "cpu":
        np.testing.assert_array_equal(got, ref)
    else:
        assert len(np.unique(got)) == len(np.unique(ref)) and matched_ious(ref, got).min(initial=1.0) >= 0.999


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("noise, cfg", [
    (0.3, MeanShiftConfig()),
    (1.5, MeanShiftConfig(min_component_px=5)),  # most objects shattered into dozens of pieces
    (0.3, MeanShiftConfig(max_pixels=300, n_seeds=8)),  # mode finding on a subsample
    (1.5, MeanShiftConfig(spatial_sigma=0.0, min_component_px=5)),  # no proximity term
])
def test_torch_path_gives_the_numpy_labels(frames, device, noise, cfg):
    pieces = []
    for i, inst in enumerate(frames):
        emb, fg = object_embeddings(inst, noise, seed=i), inst > 0
        ref = cluster_frame(emb, fg, cfg)
        assert_same_instances(ref, cluster_frame(torch.from_numpy(emb).to(device), fg, cfg), device)
        pieces.append(len(np.unique(ref[fg])))
    assert max(pieces) > (20 if noise > 1 else 1)


@pytest.mark.parametrize("device", DEVICES)
def test_torch_path_finds_the_objects(frames, device):
    """Against the known objects, not the numpy path: one instance per object, each to IoU ≥ .99."""
    for i, inst in enumerate(frames):
        emb = torch.from_numpy(object_embeddings(inst, 0.3, seed=i)).to(device)
        pred = cluster_frame(emb, inst > 0, MeanShiftConfig())
        assert np.all((pred > 0) == (inst > 0))
        assert len(np.unique(pred[pred > 0])) == len(np.unique(inst[inst > 0])) >= 2
        assert matched_ious(inst, pred).min() >= 0.99


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("k, n_per, cfg", [(2, 150, MeanShiftConfig(spatial_sigma=0.0)),
                                           (9, 150, MeanShiftConfig(spatial_sigma=0.0)),
                                           (4, 3000, MeanShiftConfig(spatial_sigma=0.0, max_pixels=500))])
def test_vmf_meanshift_on_a_device(device, k, n_per, cfg):
    emb, truth = clusters(k, n_per, seed=k)
    labels = vmf_meanshift(torch.tensor(emb, device=device), None, cfg)
    assert labels.device.type == device and labels.dtype == torch.int64
    assert_same_partition(labels.cpu().numpy(), truth)
    np.testing.assert_array_equal(labels.cpu().numpy(), vmf_meanshift(emb, None, cfg))


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("cfg", [MeanShiftConfig(min_component_px=5),
                                 MeanShiftConfig(spatial_sigma=0.0, max_pixels=300, min_component_px=5),
                                 MeanShiftConfig(kappa=2.0, spatial_sigma=0.5, min_component_px=5)])
def test_batched_frames_equal_one_by_one(frames, device, cfg):
    """Frames of different foreground sizes in one batch, with an empty frame, a 5-pixel one (fewer points than
    seeds) and one whose embeddings all coincide (seeding stops early without the proximity term)."""
    embs = [object_embeddings(inst, 1.5 if i % 2 else 0.3, seed=i) for i, inst in enumerate(frames[::3])]
    masks = [inst > 0 for inst in frames[::3]]
    h, w = masks[0].shape
    masks.append(np.zeros((h, w), bool))
    embs.append(embs[0])
    masks.append(np.zeros((h, w), bool))
    masks[-1][50, 60:65] = True
    embs.append(embs[0])
    masks.append(np.zeros((h, w), bool))
    masks[-1][20:100, 30:130] = True
    embs.append(np.zeros_like(embs[0]))
    embs[-1][0] = 1.0
    batch = torch.from_numpy(np.stack(embs)).to(device)
    got = cluster_frames(batch, masks, cfg)
    assert len(got) == len(masks)
    for e, m, g in zip(batch, masks, got):
        assert_same_instances(cluster_frame(e, m, cfg), g, device)
    assert not got[-3].any() and np.all((got[-2] > 0) == masks[-2]) and np.all(got[-1] == masks[-1])
    assert max(len(np.unique(g)) for g in got) > 3


@pytest.mark.parametrize("device", DEVICES)
def test_segment_video_on_the_device(analytic_dataset, tmp_path, device):
    """An embedding method segments a video as the numpy clustering of its own embeddings: the same on the CPU
    (frame by frame); on CUDA (network and mode finding in one batch on the GPU) nearly the same."""
    net_cfg = NetConfig(width=8, aspp_channels=16, low_level_channels=8, decoder_channels=16)
    torch.manual_seed(0)
    torch.save({"net_cfg": to_dict(net_cfg), "state_dict": EmbeddingNet(net_cfg).state_dict()}, tmp_path / "w.pt")
    cfg = EmbeddingMethodConfig(net=net_cfg, cluster=MeanShiftConfig(min_component_px=5), device=device)
    method = get_method_class("supervised")(cfg, tmp_path)
    method.load(tmp_path / "w.pt")
    ds = Dataset(analytic_dataset)
    video, labeled = ds.video(ds.video_ids[2]), ds.labeled(ds.video_ids[2])
    fgs = {f: labeled.inst(f) > 0 for f in video.frame_ids}
    preds = method.segment_video(video, video.frame_ids, fgs)
    assert list(preds) == video.frame_ids
    for f, pred in preds.items():
        ref = cluster_frame(method.embed(video.rgb(f), fgs[f]), fgs[f], cfg.cluster)
        assert pred.shape == ref.shape and np.all((pred > 0) == (ref > 0)) and len(np.unique(ref)) > 2
        if device == "cpu":
            np.testing.assert_array_equal(pred, ref)
        else:
            assert matched_ious(ref, pred).mean() >= 0.98


@pytest.mark.parametrize("cfg", [MeanShiftConfig(min_component_px=5), MeanShiftConfig(max_pixels=300, n_seeds=8),
                                 MeanShiftConfig(spatial_sigma=0.0, max_pixels=300, min_component_px=5)])
def test_static_mode_finding_gives_the_numpy_labels(frames, cfg):
    """The path CUDA graphs capture (every frame padded to ``max_pixels`` points, the kernel as one product of
    augmented vectors, all iterations, no early stop), run on the CPU: the numpy labels, one frame at a time and
    frames of different sizes in one batch. With the default ``max_pixels`` every frame is padded (743–1266
    foreground pixels), with 300 none is."""
    embs = [object_embeddings(inst, 1.5 if i % 2 else 0.3, seed=i) for i, inst in enumerate(frames)]
    masks = [inst > 0 for inst in frames]
    refs = [cluster_frame(e, m, cfg) for e, m in zip(embs, masks)]
    tensors = [torch.from_numpy(e) for e in embs]
    for e, m, ref in zip(tensors, masks, refs):
        np.testing.assert_array_equal(_cluster([e], [m], cfg, static=True)[0], ref)
    for got, ref in zip(_cluster(tensors, masks, cfg, static=True), refs):
        np.testing.assert_array_equal(got, ref)
    assert max(len(np.unique(r)) for r in refs) > 3
