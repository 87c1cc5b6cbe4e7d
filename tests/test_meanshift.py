"""vMF mean-shift with the proximity term, connected-component splitting and small-part absorption."""
import numpy as np
import pytest

from selfseg.method.meanshift import (MeanShiftConfig, _merge_modes, _subsample, absorb_small, cluster_frame,
                                     split_components, vmf_meanshift)


def unit(x):
    return x / np.linalg.norm(x, axis=-1, keepdims=True)


def clusters(k, n_per, dim=16, noise=0.08, seed=0):
    rng = np.random.default_rng(seed)
    centers = unit(rng.normal(size=(k, dim)))
    truth = np.repeat(np.arange(k), n_per)
    return unit(centers[truth] + noise * rng.normal(size=(k * n_per, dim))), truth


def assert_same_partition(labels, truth):
    """One label per true cluster and one true cluster per label."""
    pairs = set(zip(labels.tolist(), truth.tolist()))
    assert len(pairs) == len(set(truth.tolist())) == len(set(labels.tolist()))


@pytest.mark.parametrize("k", [2, 5, 9])
def test_recovers_k_clusters_without_being_told(k):
    emb, truth = clusters(k, 150, seed=k)
    labels = vmf_meanshift(emb, None, MeanShiftConfig(spatial_sigma=0.0))
    assert_same_partition(labels, truth)
    assert labels.min() == 0 and np.bincount(labels).tolist() == sorted(np.bincount(labels).tolist(), reverse=True)


def test_subsampled_mode_finding_assigns_every_point():
    emb, truth = clusters(4, 3000, seed=1)
    labels = vmf_meanshift(emb, None, MeanShiftConfig(spatial_sigma=0.0, max_pixels=500))
    assert labels.shape == truth.shape
    assert_same_partition(labels, truth)


def test_spatial_term_needs_positions():
    emb, _ = clusters(2, 10)
    with pytest.raises(ValueError, match="xy"):
        vmf_meanshift(emb, None, MeanShiftConfig(spatial_sigma=0.1))


def bridged_blobs(h=60, w=120):
    """Two 30×30 squares far apart, joined by a 1-pixel bridge: one connected foreground region."""
    fg = np.zeros((h, w), bool)
    fg[15:45, 5:35] = True
    fg[15:45, 85:115] = True
    fg[30, 35:85] = True
    return fg


def test_proximity_term_splits_identical_blobs_far_apart():
    fg = bridged_blobs()
    rng = np.random.default_rng(0)
    emb = unit(np.array([1.0, 0.5, -0.2, 0.3])[:, None, None] + 0.02 * rng.normal(size=(4,) + fg.shape))
    emb = unit(emb.transpose(1, 2, 0)).transpose(2, 0, 1)
    plain = cluster_frame(emb, fg, MeanShiftConfig(spatial_sigma=0.0, min_component_px=10))
    assert set(np.unique(plain[fg])) == {1}  # same features and connected: components cannot split it
    near = cluster_frame(emb, fg, MeanShiftConfig(spatial_sigma=0.12, merge_xy=0.3, min_component_px=10))
    left, right = near[15:45, 5:35], near[15:45, 85:115]
    assert len(np.unique(left)) == 1 and len(np.unique(right)) == 1
    assert left[0, 0] != right[0, 0] and left[0, 0] > 0 and right[0, 0] > 0
    assert np.all((near > 0) == fg)


def test_clusters_are_split_into_components_and_small_parts_absorbed_or_dropped():
    h, w = 40, 60
    fg = np.zeros((h, w), bool)
    fg[5:20, 5:20] = True  # square A
    fg[5:20, 40:55] = True  # square B, same features as A, not touching
    fg[30:33, 30:33] = True  # isolated 9-pixel speck
    emb = np.zeros((3, h, w), np.float32)
    emb[0] = 1.0
    emb[:, 10:13, 10:13] = np.array([0.0, 1.0, 0.0])[:, None, None]  # a 9-px patch inside A, other features
    inst = cluster_frame(emb, fg, MeanShiftConfig(spatial_sigma=0.0, min_component_px=20))
    a, b = inst[5:20, 5:20], inst[5:20, 40:55]
    assert len(np.unique(a)) == 1 and len(np.unique(b)) == 1 and a[0, 0] != b[0, 0]  # patch absorbed into A
    assert np.all(inst[30:33, 30:33] == 0)  # small and isolated: dropped
    assert sorted(np.unique(inst).tolist()) == [0, 1, 2]
    kept = cluster_frame(emb, fg, MeanShiftConfig(spatial_sigma=0.0, min_component_px=1))
    assert len(np.unique(kept[10:13, 10:13])) == 1 and kept[11, 11] != kept[5, 5]
    assert len(np.unique(kept[fg])) == 4  # A, patch, B, speck


def test_split_and_absorb_helpers():
    lab = np.array([[1, 1, 0, 1],
                    [0, 0, 0, 1],
                    [2, 2, 0, 0]])
    comps = split_components(lab, connectivity=4)
    assert len(np.unique(comps[comps > 0])) == 3 and comps[0, 0] != comps[0, 3]
    grown = np.array([[1, 1, 1, 2],
                      [1, 1, 1, 1],
                      [3, 3, 0, 4]])
    out = absorb_small(grown, min_px=2)  # 2 (1 px) joins 1; 3 (2 px) stays; 4 (1 px) touches only 1
    assert out[0, 3] == out[0, 0] == out[2, 3] and out[2, 0] == out[2, 1] != out[0, 0]
    assert sorted(np.unique(out).tolist()) == [0, 1, 2]


def test_cluster_frame_edge_cases():
    cfg = MeanShiftConfig()
    assert np.all(cluster_frame(np.ones((4, 5, 6), np.float32) / 2, np.zeros((5, 6), bool), cfg) == 0)
    with pytest.raises(ValueError, match="D×H×W"):
        cluster_frame(np.ones((4, 5, 6)), np.ones((6, 5), bool), cfg)
    with pytest.raises(ValueError, match="connectivity"):
        MeanShiftConfig(connectivity=6)


@pytest.mark.parametrize("connectivity", [4, 8])
def test_split_components_numbers_as_whole_frame_labelling(connectivity):
    """Each label is labelled inside its bounding box; the ids must be those of labelling the whole frame label by
    label (OpenCV's 8-connected labelling works on 2×2 blocks, so a crop at odd coordinates would renumber)."""
    import cv2

    rng = np.random.default_rng(connectivity)
    for t in range(200):
        h, w = rng.integers(3, 40, 2)
        labels = rng.integers(-1, rng.integers(2, 12), (h, w))
        if t % 2:  # blocky maps: components of many shapes and sizes
            labels = cv2.resize(labels.astype(np.int16), (int(w) * 3, int(h) * 3), interpolation=cv2.INTER_NEAREST)
        want, nxt = np.zeros(labels.shape, np.int32), 1
        for c in np.unique(labels[labels > 0]):
            n, comp = cv2.connectedComponents((labels == c).astype(np.uint8), connectivity=connectivity)
            want[comp > 0] = comp[comp > 0] + nxt - 1
            nxt += n - 1
        np.testing.assert_array_equal(split_components(labels, connectivity), want)


def test_border_counts_count_every_4_neighbour_pair():
    from selfseg.method.meanshift import _border_counts

    rng = np.random.default_rng(3)
    for _ in range(50):
        inst = rng.integers(0, 6, tuple(rng.integers(2, 15, 2)))
        want: dict = {}
        for (y, x), a in np.ndenumerate(inst):
            for y2, x2 in ((y, x + 1), (y + 1, x)):
                if y2 < inst.shape[0] and x2 < inst.shape[1] and a > 0 and inst[y2, x2] > 0 and inst[y2, x2] != a:
                    b = int(inst[y2, x2])
                    want.setdefault(int(a), {}).setdefault(b, 0)
                    want.setdefault(b, {}).setdefault(int(a), 0)
                    want[int(a)][b] += 1
                    want[b][int(a)] += 1
        assert _border_counts(inst, int(inst.max())) == want


def test_modes_merge_densest_first_into_the_first_close_kept_mode():
    """A chain a–b–c (a, c not close): b joins the denser a, c then starts its own cluster; d is close to both a and
    c and joins a, the first kept; e is close to a in embedding but farther than merge_xy, so it stays apart."""
    deg = np.deg2rad
    ang = {"a": 0.0, "b": 40.0, "c": 80.0, "d": 40.0, "e": 0.0}  # cos 40° = .77 ≥ .7, cos 80° = .17
    mu = np.array([[np.cos(deg(v)), np.sin(deg(v)), 0.0] for v in ang.values()], np.float32)
    p = np.array([[0, 0], [0.1, 0], [0.2, 0], [0.1, 0.1], [0.9, 0]], np.float32)
    density = np.array([5.0, 4.0, 3.0, 2.0, 1.0], np.float32)
    cfg = MeanShiftConfig(merge_threshold=0.7, merge_xy=0.3)
    np.testing.assert_array_equal(_merge_modes(mu, p, density, cfg), [0, 0, 1, 0, 2])
    np.testing.assert_array_equal(_merge_modes(mu, None, density, cfg), [0, 0, 1, 0, 0])
    c_densest = np.array([4.0, 3.0, 5.0, 2.0, 1.0], np.float32)  # c keeps id 0, a starts id 1, b and d join c
    np.testing.assert_array_equal(_merge_modes(mu, p, c_densest, cfg), [1, 0, 0, 0, 2])


@pytest.mark.parametrize("n", [1, 4000, 4001, 15002, 200000, 250000])
def test_subsample_is_the_sorted_seeded_choice(n):
    """The points mode finding runs on: numpy's seeded choice without replacement, sorted (drawn without its final
    shuffle and sorted through a mask, the same set)."""
    cfg = MeanShiftConfig(max_pixels=4000, seed=3)
    want = np.arange(n) if n <= 4000 else np.sort(np.random.default_rng(3).choice(n, 4000, replace=False))
    np.testing.assert_array_equal(_subsample(n, cfg), want)
