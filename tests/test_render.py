"""Blender renderer: smoke tests and exactness of the ground-truth pass against ray casting."""
import numpy as np
import pytest
import trimesh

from selfseg.generate.objects import ObjectModel
from selfseg.generate.render import BlenderScene, RenderConfig, intrinsics, sample_appearance
from selfseg.raycast import RaycastScene, look_at

W, H = 64, 48
TABLE_ID = 999


def _model(name: str, mesh: trimesh.Trimesh, seed: int) -> ObjectModel:
    lo, hi = mesh.bounds
    uv = (mesh.vertices[:, :2] - lo[:2]) / (hi[:2] - lo[:2])
    tex = np.random.default_rng(seed).integers(0, 255, (32, 32, 3)).astype(np.uint8)
    return ObjectModel(name=name, vertices=np.asarray(mesh.vertices), faces=np.asarray(mesh.faces), uv=uv,
                       texture=tex, collision_parts=None, nonconvex=False, source="test")


def _pose(x: float, y: float, z: float, yaw_deg: float = 0.0) -> np.ndarray:
    T = trimesh.transformations.rotation_matrix(np.radians(yaw_deg), [0, 0, 1])
    T[:3, 3] = (x, y, z)
    return T


@pytest.fixture(scope="module")
def objects():
    box = _model("box", trimesh.creation.box(extents=(0.10, 0.07, 0.06)), 1)
    cyl = _model("cyl", trimesh.creation.cylinder(radius=0.035, height=0.12, sections=32), 2)
    return [(1, box, _pose(-0.05, 0.0, 0.03, 20)), (300, cyl, _pose(0.07, 0.04, 0.06))]  # 300: uses the high byte of the id colour


def _raycast(objects, K, T_wc, w, h):
    table = trimesh.creation.box(extents=(4.0, 4.0, 0.01))
    table.apply_translation((0, 0, -0.005))
    scene = RaycastScene.from_meshes([m.trimesh() for _, m, _ in objects] + [table],
                                     [T for _, _, T in objects] + [np.eye(4)], [i for i, _, _ in objects] + [TABLE_ID])
    depth, inst, _ = scene.render(K, T_wc, w, h)
    return depth, np.where(inst == TABLE_ID, 0, inst)


@pytest.mark.slow
def test_workbench_two_frames_match_raycast(objects):
    """Two 64×48 Workbench frames: depth and instance ids agree with an independent ray cast."""
    K = intrinsics(W, H, 58.0)
    cams = [look_at([0.45, 0.1, 0.35], [0, 0, 0.04]), look_at([0.44, 0.12, 0.36], [0, 0, 0.04])]
    with BlenderScene(objects, sample_appearance(np.random.default_rng(0)), W, H, K,
                      RenderConfig(renderer="workbench")) as scene:
        for T_wc in cams:
            rgb, depth, inst = scene.render(T_wc)
            assert rgb.shape == (H, W, 3) and rgb.dtype == np.uint8 and rgb.std() > 5
            assert depth.dtype == np.float32 and inst.dtype == np.uint16
            ref_depth, ref_inst = _raycast(objects, K, T_wc, W, H)
            assert set(np.unique(inst)) == {0, 1, 300}
            assert (inst == ref_inst).mean() > 0.995
            both = (depth > 0) & (ref_depth > 0)
            assert both.mean() > 0.9  # the table fills the view
            assert np.median(np.abs(depth[both] - ref_depth[both])) < 1e-4


@pytest.mark.slow
def test_cycles_frame(objects):
    """One Cycles frame: a lit, non-constant image whose ground truth equals Workbench's."""
    K = intrinsics(W, H, 58.0)
    T_wc = look_at([0.45, -0.1, 0.35], [0, 0, 0.04])
    with BlenderScene(objects, sample_appearance(np.random.default_rng(1)), W, H, K,
                      RenderConfig(renderer="cycles", samples=2, device="cpu")) as scene:
        assert scene.device == "cycles-cpu"
        rgb, depth, inst = scene.render(T_wc)
    assert rgb.shape == (H, W, 3) and rgb.std() > 5 and 20 < rgb.mean() < 245
    ref_depth, ref_inst = _raycast(objects, K, T_wc, W, H)
    assert (inst == ref_inst).mean() > 0.995
    # the objects are visible in the image: their pixels differ from the table's
    obj = inst > 0
    assert np.abs(rgb[obj].mean(0) - rgb[~obj].mean(0)).max() > 5


def test_intrinsics_convention():
    K = intrinsics(640, 480, 90.0)
    assert K[0, 0] == pytest.approx(320.0) and K[1, 1] == pytest.approx(320.0)
    assert K[0, 2] == 319.5 and K[1, 2] == 239.5


def test_bad_resolution_rejected(objects):
    with pytest.raises(ValueError, match="resolution"):
        BlenderScene(objects, sample_appearance(np.random.default_rng(0)), 0, 48, intrinsics(64, 48, 58.0))
