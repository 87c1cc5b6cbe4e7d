"""Blender (bpy 5.0) renderer for generated scenes: RGB, planar depth and instance maps per frame.

Each frame is rendered twice in the same Blender scene:

* the **image pass**: Cycles (photo-real, GPU if one exists, else CPU) or Workbench (fast, for
  tests) renders the 8-bit RGB image;
* the **ground-truth pass**: Workbench with flat lighting, one exact colour per object and
  anti-aliasing off renders depth (planar z, metres) and instance ids at pixel centres, so ids
  are never blended. It is the same for both renderers.

Units: metres; world z up, table top at z = 0. Camera poses are OpenCV ``T_world_cam`` (x right,
y down, z forward); Blender's camera looks down its −z axis with y up, so its matrix is
``T_world_cam @ diag(1, −1, −1, 1)``. Intrinsics follow the OpenCV pixel-centre convention.
"""
from __future__ import annotations

import os

os.environ.setdefault("OPENCV_IO_ENABLE_OPENEXR", "1")  # before cv2 reads its first EXR

import contextlib
import math
import shutil
import signal
import sys
import tempfile
import threading
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np

from selfseg.generate.depth_noise import DepthNoiseConfig
from selfseg.generate.textures import table_texture

BLENDER_BACKGROUND_DEPTH = 1e9  # Blender's Z pass writes 1e10 where no surface is hit
TABLE_SIZE_M = 4.0  # side of the square table plane (larger than the physics table: no visible edge)
TABLE_TILE_M = 0.5  # side of the table covered by one copy of its texture image
ID_SCALE = 255.0  # instance k is rendered as colour (k mod 256, k div 256, 0) / ID_SCALE


@dataclass
class RenderConfig:
    """How frames are rendered. The Cycles defaults come from the settings sweep in bench/bench_generate.py."""

    renderer: Literal["cycles", "workbench"] = "cycles"
    samples: int = 4  # Cycles samples per pixel (denoised)
    denoise: bool = True  # OpenImageDenoise (fast quality, colour + albedo inputs) on the Cycles image
    max_bounces: int = 3  # Cycles total light-path bounces (diffuse 2, glossy 2, no caustics)
    device: Literal["auto", "cpu"] = "auto"  # auto: Cycles on a GPU when one exists
    threads: int = 0  # render threads, 0 = all cores
    depth_noise: DepthNoiseConfig | None = None  # sensor noise on the written depth (depth_noise.py); None: exact

    def __post_init__(self) -> None:
        if self.samples < 1:
            raise ValueError(f"render.samples must be >= 1, got {self.samples}")
        if self.max_bounces < 0:
            raise ValueError(f"render.max_bounces must be >= 0, got {self.max_bounces}")


def intrinsics(width: int, height: int, hfov_deg: float) -> np.ndarray:
    """3×3 K (OpenCV pixel-centre convention) of a pinhole camera with horizontal FOV ``hfov_deg``."""
    fx = width / (2.0 * math.tan(math.radians(hfov_deg) / 2.0))
    return np.array([[fx, 0.0, width / 2.0 - 0.5], [0.0, fx, height / 2.0 - 0.5], [0.0, 0.0, 1.0]])


# ---- per-scene appearance ------------------------------------------------------------------------
def sample_appearance(rng: np.random.Generator) -> dict:
    """Random table texture and lighting of one scene (JSON-serialisable; recorded in scene_info).

    Angles in degrees, sun strength in W/m², area-light power in W, positions in world metres.
    """
    return {
        "table": {"texture_seed": int(rng.integers(2**31))},
        "sun": {"elevation_deg": float(round(rng.uniform(35.0, 80.0), 2)), "azimuth_deg": float(round(rng.uniform(0, 360), 2)),
                "strength": float(round(rng.uniform(0.8, 2.0), 3)), "angle_deg": float(round(rng.uniform(1.0, 15.0), 2))},
        "area": {"position": [float(round(v, 3)) for v in (rng.uniform(-1, 1), rng.uniform(-1, 1), rng.uniform(1.2, 2.0))],
                 "power_w": float(round(rng.uniform(20.0, 80.0), 2)), "size_m": float(round(rng.uniform(0.5, 1.5), 3))},
        "world": {"color": rng.uniform(0.6, 1.0, 3).round(4).tolist(), "strength": float(round(rng.uniform(0.15, 0.4), 3))},
    }


@contextlib.contextmanager
def _blender_quiet():
    """Silence Blender's C-level output for a block: "Fra:"/"Saved:" lines and the harmless EGL
    warnings of headless Workbench. Blender's real failures still raise from bpy.ops."""
    sys.stdout.flush()
    sys.stderr.flush()
    saved = [os.dup(1), os.dup(2)]
    devnull = os.open(os.devnull, os.O_WRONLY)
    try:
        os.dup2(devnull, 1)
        os.dup2(devnull, 2)
        yield
    finally:
        os.dup2(saved[0], 1)
        os.dup2(saved[1], 2)
        for fd in (*saved, devnull):
            os.close(fd)


# ---- Blender scene ---------------------------------------------------------------------------------
def _enable_gpu() -> bool:
    """Enable the first GPU compute backend Cycles finds; False when there is none."""
    import bpy

    prefs = bpy.context.preferences.addons["cycles"].preferences
    for backend in ("OPTIX", "CUDA", "HIP", "ONEAPI", "METAL"):
        try:
            prefs.compute_device_type = backend
        except TypeError:
            continue
        prefs.get_devices()
        gpus = [d for d in prefs.devices if d.type == backend]
        if gpus:
            for d in prefs.devices:
                d.use = d.type == backend
            return True
    prefs.compute_device_type = "NONE"
    return False


def _image_from_array(name: str, rgb: np.ndarray):
    """A packed Blender image from uint8 H×W×3 (row 0 = top, as numpy and trimesh textures)."""
    import bpy

    h, w = rgb.shape[:2]
    img = bpy.data.images.new(name, width=w, height=h, alpha=False)
    rgba = np.concatenate([rgb[::-1].astype(np.float32) / 255.0, np.ones((h, w, 1), np.float32)], axis=2)
    img.pixels.foreach_set(rgba.ravel())
    img.pack()
    return img


def _textured_material(name: str, image, roughness: float):
    import bpy

    mat = bpy.data.materials.new(name)  # Blender 5 materials come with a node tree (use_nodes is deprecated)
    nt = mat.node_tree
    bsdf = nt.nodes["Principled BSDF"]
    tex = nt.nodes.new("ShaderNodeTexImage")
    tex.image = image
    nt.links.new(tex.outputs["Color"], bsdf.inputs["Base Color"])
    bsdf.inputs["Roughness"].default_value = roughness
    return mat


def _mark_sharp_edges(me, vertices: np.ndarray, faces: np.ndarray, angle_deg: float = 35.0) -> None:
    """Smooth shading except across edges whose faces meet at more than ``angle_deg``."""
    import trimesh

    me.shade_smooth()
    tm = trimesh.Trimesh(vertices, faces, process=False)
    sharp_pairs = tm.face_adjacency_edges[tm.face_adjacency_angles > math.radians(angle_deg)]
    if not len(sharp_pairs):
        return
    ev = np.empty(len(me.edges) * 2, np.int64)
    me.edges.foreach_get("vertices", ev)
    ev = np.sort(ev.reshape(-1, 2), axis=1)
    key = ev[:, 0] * len(vertices) + ev[:, 1]
    sp = np.sort(sharp_pairs, axis=1)
    flags = np.isin(key, sp[:, 0] * len(vertices) + sp[:, 1])
    attr = me.attributes.get("sharp_edge") or me.attributes.new("sharp_edge", "BOOLEAN", "EDGE")
    attr.data.foreach_set("value", flags.tolist())


def _mesh_object(name: str, vertices: np.ndarray, faces: np.ndarray, uv: np.ndarray | None, material):
    import bpy

    me = bpy.data.meshes.new(name)
    me.from_pydata(np.asarray(vertices, float).tolist(), [], np.asarray(faces, int).tolist())
    if uv is not None:
        layer = me.uv_layers.new(name="UVMap")
        loop_vi = np.empty(len(me.loops), np.int64)
        me.loops.foreach_get("vertex_index", loop_vi)
        layer.data.foreach_set("uv", np.asarray(uv, np.float32)[loop_vi].ravel())
    me.materials.append(material)
    me.validate()
    me.update()
    ob = bpy.data.objects.new(name, me)
    bpy.context.scene.collection.objects.link(ob)
    return ob, me


class BlenderScene:
    """One scene in Blender: textured objects at fixed world poses on a table, lights, a camera.

    objects: list of (instance id ≥ 1, ObjectModel, T_world_obj 4×4). ``render(T_world_cam)``
    returns (rgb uint8 H×W×3, depth float32 metres with 0 = background, inst uint16).
    Blender is global state: only one BlenderScene is live per process.
    """

    def __init__(self, objects: list, appearance: dict, width: int, height: int, K: np.ndarray,
                 cfg: RenderConfig = RenderConfig(), seed: int = 0):
        import bpy

        if width <= 0 or height <= 0:
            raise ValueError(f"resolution must be positive, got {width}x{height}")
        self.width, self.height, self.K, self.cfg = width, height, np.asarray(K, float), cfg
        if not (np.isclose(self.K[0, 2], width / 2 - 0.5) and np.isclose(self.K[1, 2], height / 2 - 0.5)
                and np.isclose(self.K[0, 0], self.K[1, 1])):
            raise ValueError("BlenderScene needs square pixels and a centred principal point (see intrinsics())")
        with _blender_quiet():
            bpy.ops.wm.read_factory_settings(use_empty=True)
        self.scene = bpy.context.scene
        self._setup_output()
        self.instance_ids = self._add_objects(objects)
        self._add_table(appearance["table"]["texture_seed"])
        self._add_lights(appearance)
        self.camera = self._add_camera()
        self._tmp = Path(tempfile.mkdtemp(prefix="selfseg_render_"))
        self._sigints: list[int] = []  # SIGINTs noted while rendering (see __enter__)
        self._add_ground_truth_outputs()
        self._gpu = False
        if cfg.renderer == "cycles":
            self._setup_cycles(seed)

    def _setup_output(self) -> None:
        """Resolution (px, square pixels), no dithering, render threads, Standard view transform, Z pass."""
        sc, cfg = self.scene, self.cfg
        sc.render.resolution_x, sc.render.resolution_y, sc.render.resolution_percentage = self.width, self.height, 100
        sc.render.pixel_aspect_x = sc.render.pixel_aspect_y = 1.0
        sc.render.dither_intensity = 0.0
        sc.render.threads_mode = "FIXED" if cfg.threads else "AUTO"
        if cfg.threads:
            sc.render.threads = cfg.threads
        sc.view_settings.view_transform = "Standard"
        sc.view_layers[0].use_pass_z = True

    def _add_objects(self, objects: list) -> list[int]:
        """Textured objects at their T_world_obj (m); the flat colour encodes the instance id for the
        ground-truth pass. Returns the instance ids."""
        import mathutils

        instance_ids = []
        for inst_id, model, T in objects:
            if not 1 <= inst_id < 65536:
                raise ValueError(f"instance id {inst_id} outside [1, 65535]")
            img = _image_from_array(f"tex_{model.name}", np.asarray(model.texture, np.uint8))
            mat = _textured_material(f"mat_{model.name}", img, roughness=0.5)
            ob, me = _mesh_object(f"inst_{inst_id}", model.vertices, model.faces, model.uv, mat)
            _mark_sharp_edges(me, np.asarray(model.vertices, float), np.asarray(model.faces, np.int64))
            ob.matrix_world = mathutils.Matrix(np.asarray(T, float).tolist())
            ob.color = ((inst_id % 256) / ID_SCALE, (inst_id // 256) / ID_SCALE, 0.0, 1.0)
            ob.pass_index = inst_id
            instance_ids.append(inst_id)
        return instance_ids

    def _add_table(self, texture_seed: int) -> None:
        """The table: a TABLE_SIZE_M square plane at z = 0 with the scene's procedural texture, tiled
        every TABLE_TILE_M; id colour 0 (background)."""
        half, reps = TABLE_SIZE_M / 2, TABLE_SIZE_M / TABLE_TILE_M
        timg = _image_from_array("table_tex", table_texture(texture_seed))
        tmat = _textured_material("table_mat", timg, roughness=0.7)
        table, _ = _mesh_object("table", np.array([[-half, -half, 0], [half, -half, 0], [half, half, 0], [-half, half, 0]]),
                                np.array([[0, 1, 2], [0, 2, 3]]), np.array([[0, 0], [reps, 0], [reps, reps], [0, reps]]),
                                tmat)
        table.color = (0.0, 0.0, 0.0, 1.0)

    def _add_lights(self, appearance: dict) -> None:
        """Sun (direction from elevation and azimuth, deg), area light aimed at the world origin (position in m)
        and the world background, from ``appearance`` (see :func:`sample_appearance`)."""
        import bpy
        import mathutils

        sc = self.scene
        sun_p = appearance["sun"]
        sun = bpy.data.lights.new("sun", "SUN")
        sun.energy = sun_p["strength"]
        sun.angle = math.radians(sun_p["angle_deg"])
        sun_ob = bpy.data.objects.new("sun", sun)
        sun_ob.rotation_euler = (math.radians(90 - sun_p["elevation_deg"]), 0.0, math.radians(sun_p["azimuth_deg"]))
        sc.collection.objects.link(sun_ob)
        area_p = appearance["area"]
        area = bpy.data.lights.new("area", "AREA")
        area.energy, area.size = area_p["power_w"], area_p["size_m"]
        area_ob = bpy.data.objects.new("area", area)
        area_ob.location = area_p["position"]
        area_ob.rotation_euler = (mathutils.Vector((0, 0, 0)) - mathutils.Vector(area_p["position"])).to_track_quat("-Z", "Y").to_euler()
        sc.collection.objects.link(area_ob)
        world = bpy.data.worlds.new("world")
        bg = world.node_tree.nodes["Background"]
        bg.inputs["Color"].default_value = (*appearance["world"]["color"], 1.0)
        bg.inputs["Strength"].default_value = appearance["world"]["strength"]
        sc.world = world

    def _add_camera(self):
        """The scene camera with the focal length of K (horizontal sensor fit, principal point at the
        centre, clipping 0.01–50 m); placed by :meth:`set_camera`."""
        import bpy

        cam = bpy.data.cameras.new("camera")
        cam.sensor_fit = "HORIZONTAL"
        cam.sensor_width = 36.0
        cam.lens = self.K[0, 0] * cam.sensor_width / self.width
        cam.clip_start, cam.clip_end = 0.01, 50.0
        camera = bpy.data.objects.new("camera", cam)
        self.scene.collection.objects.link(camera)
        self.scene.camera = camera
        return camera

    def _add_ground_truth_outputs(self) -> None:
        """Compositor for the ground-truth pass: depth (m) and flat colour to 32-bit EXR in the temporary folder."""
        import bpy

        tree = bpy.data.node_groups.new("gt_outputs", "CompositorNodeTree")
        self.scene.compositing_node_group = tree
        rl = tree.nodes.new("CompositorNodeRLayers")
        out = tree.nodes.new("CompositorNodeOutputFile")
        out.directory = str(self._tmp) + os.sep
        out.file_name = "gt_"
        out.format.media_type = "IMAGE"
        out.format.file_format = "OPEN_EXR"
        out.format.color_depth = "32"
        out.format.exr_codec = "NONE"
        out.file_output_items.new("FLOAT", "depth")
        out.file_output_items.new("RGBA", "ids")
        tree.links.new(rl.outputs["Depth"], out.inputs["depth"])
        tree.links.new(rl.outputs["Image"], out.inputs["ids"])

    def _setup_cycles(self, seed: int) -> None:
        cy = self.scene.cycles
        with _blender_quiet():  # Cycles warns about every missing GPU library
            self._gpu = self.cfg.device == "auto" and _enable_gpu()
        cy.device = "GPU" if self._gpu else "CPU"
        cy.samples = self.cfg.samples
        cy.use_adaptive_sampling = False
        cy.use_denoising = self.cfg.denoise
        if self.cfg.denoise:
            # FAST quality with the albedo guide keeps textures sharp; HIGH/BALANCED cost about 2 s
            # per frame on 2 CPU cores (bench/bench_generate.py).
            cy.denoiser = "OPENIMAGEDENOISE"
            cy.denoising_quality = "FAST"
            cy.denoising_input_passes = "RGB_ALBEDO"
            cy.denoising_prefilter = "FAST"
            cy.denoising_use_gpu = self._gpu
        cy.max_bounces = self.cfg.max_bounces
        cy.diffuse_bounces = min(2, self.cfg.max_bounces)
        cy.glossy_bounces = min(2, self.cfg.max_bounces)
        cy.transmission_bounces = cy.volume_bounces = cy.transparent_max_bounces = 0
        cy.caustics_reflective = cy.caustics_refractive = False
        cy.use_light_tree = False
        cy.seed = seed
        cy.use_animated_seed = False

    @property
    def device(self) -> str:
        """What renders the image pass: 'cycles-gpu', 'cycles-cpu' or 'workbench'."""
        return "workbench" if self.cfg.renderer == "workbench" else ("cycles-gpu" if self._gpu else "cycles-cpu")

    def set_camera(self, T_world_cam: np.ndarray) -> None:
        import mathutils

        T_blender = np.asarray(T_world_cam, float) @ np.diag([1.0, -1.0, -1.0, 1.0])
        self.camera.matrix_world = mathutils.Matrix(T_blender.tolist())

    def render(self, T_world_cam: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(rgb uint8 H×W×3, depth float32 m (0 = background), inst uint16) seen from ``T_world_cam``."""
        self.raise_if_interrupted()
        self.set_camera(T_world_cam)
        rgb = self.render_rgb()
        depth, inst = self.render_ground_truth()
        self.raise_if_interrupted()
        return rgb, depth, inst

    def raise_if_interrupted(self) -> None:
        """Raise KeyboardInterrupt if Ctrl-C came since the last check (call it between frames)."""
        if self._sigints:
            self._sigints.clear()
            raise KeyboardInterrupt

    def render_rgb(self) -> np.ndarray:
        """The image pass, uint8 H×W×3 RGB."""
        import bpy
        import cv2

        sc = self.scene
        sc.render.use_compositing = False
        sc.render.film_transparent = False
        if self.cfg.renderer == "cycles":
            sc.render.engine = "CYCLES"
        else:
            sc.render.engine = "BLENDER_WORKBENCH"
            sh = sc.display.shading
            sh.light, sh.color_type = "STUDIO", "TEXTURE"
            sh.show_shadows, sh.show_cavity = True, False
            sc.display.render_aa = "FXAA"  # 8× AA with shadows costs ~10× more
        sc.render.image_settings.file_format = "PNG"
        sc.render.image_settings.color_mode = "RGB"
        sc.render.image_settings.color_depth = "8"
        path = self._tmp / "rgb.png"
        sc.render.filepath = str(path)
        with _blender_quiet():
            bpy.ops.render.render(write_still=True)
        img = cv2.imread(str(path), cv2.IMREAD_COLOR)
        path.unlink(missing_ok=True)  # never read a stale frame
        if img is None:
            raise RuntimeError(f"{path}: Blender wrote no image")
        return np.ascontiguousarray(img[:, :, ::-1])

    def render_ground_truth(self) -> tuple[np.ndarray, np.ndarray]:
        """The ground-truth pass: planar depth (float32 m, 0 = background) and instance ids (uint16)."""
        import bpy
        import cv2

        sc = self.scene
        sc.render.engine = "BLENDER_WORKBENCH"
        sc.render.use_compositing = True
        sc.render.film_transparent = True
        sh = sc.display.shading
        sh.light, sh.color_type = "FLAT", "OBJECT"
        sh.show_shadows = sh.show_cavity = sh.show_object_outline = False
        sh.show_specular_highlight = False
        sc.display.render_aa = "OFF"
        with _blender_quiet():
            bpy.ops.render.render(write_still=False)
        depth_raw, ids_raw = (cv2.imread(str(self._tmp / f"gt_{n}.exr"), cv2.IMREAD_UNCHANGED) for n in ("depth", "ids"))
        for n in ("depth", "ids"):
            (self._tmp / f"gt_{n}.exr").unlink(missing_ok=True)  # never read a stale frame
        if depth_raw is None or ids_raw is None:
            raise RuntimeError(f"{self._tmp}: Blender wrote no ground-truth EXR (is OpenEXR enabled in cv2?)")
        depth = depth_raw[..., 0] if depth_raw.ndim == 3 else depth_raw
        depth = np.where((depth > 0) & (depth < BLENDER_BACKGROUND_DEPTH), depth, 0).astype(np.float32)
        # cv2 gives BGRA: red (low byte of the id) is channel 2, green (high byte) channel 1
        lo = np.rint(ids_raw[..., 2] * ID_SCALE).astype(np.int64)
        hi = np.rint(ids_raw[..., 1] * ID_SCALE).astype(np.int64)
        inst = np.where(ids_raw[..., 3] > 0.5, lo + 256 * hi, 0)
        known = np.isin(inst, [0, *self.instance_ids])
        if not known.all():
            raise RuntimeError(f"ground-truth pass decoded unknown instance ids {np.unique(inst[~known])[:5]}")
        return depth, inst.astype(np.uint16)

    def close(self) -> None:
        """Remove the temporary render folder (Blender state is reset by the next scene)."""
        shutil.rmtree(self._tmp, ignore_errors=True)

    def __enter__(self) -> "BlenderScene":
        """Within the block Ctrl-C is noted and raised between frames: Blender runs Python callbacks while it
        renders and frees engines, and a KeyboardInterrupt raised in them is printed and swallowed."""
        self._sigints.clear()
        self._previous_sigint = None
        if threading.current_thread() is threading.main_thread() and \
                signal.getsignal(signal.SIGINT) is signal.default_int_handler:
            self._previous_sigint = signal.signal(signal.SIGINT, lambda signum, frame: self._sigints.append(signum))
        return self

    def __exit__(self, exc_type, *exc) -> None:
        self.close()
        if self._previous_sigint is not None:
            signal.signal(signal.SIGINT, self._previous_sigint)
        if exc_type is None:
            self.raise_if_interrupted()
