"""Real captures: Import Cameras of a COLMAP folder (sparse/0 + images) or a transforms.json
folder, and *Poses from Photos* (a folder of photos or a video -> COLMAP poses, then imported).

Both run in one :class:`CaptureJob` (the add-on's background :class:`jobs.Job`): the core reads the
capture (``nm.read_capture``), estimates poses first for Poses from Photos (``nm.frames_from_video`` for a
video, ``nm.estimate_poses``), and writes undistorted copies of the photos when their lenses distort
(``nm.undistorted_images``; Blender cameras are pinhole). The thread never touches bpy; the operator
then makes, on the main thread (:func:`build_capture`):

* one camera per photo in the "NeuMesh Dataset" collection, the photo (undistorted) as its background;
* "NeuMesh Points": the capture's sparse points as a mesh of loose vertices with their colours as the
  point colour attribute "Color", drawn as small spheres by a Mesh to Points modifier;
* "NeuMesh Box": an Empty drawn as a cube around the object region (the core's ``capture_object_box``).
"""
from __future__ import annotations

import os

import bpy
from bpy.props import BoolProperty, FloatProperty, IntProperty, StringProperty

from ..runtime._np import np
from ..runtime import core, jobs
from ..runtime.errors import UserError
from ..scene import camera
from ..render.images import DATASET_COLLECTION

POINTS_NAME = "NeuMesh Points"
BOX_NAME = "NeuMesh Box"
VIDEO_EXTENSIONS = (".mp4", ".mov", ".avi", ".mkv", ".webm", ".m4v", ".mts")


# --------------------------------------------------------------------------------------------- numpy only
def box_bounds(obj):
    """World-space (lo (3,), hi (3,)) of a "NeuMesh Box" Empty as the artist left it (moved, scaled,
    rotated: the axis-aligned bounds of its 8 corners). The Empty's local cube is [-1, 1]^3 times
    ``empty_display_size`` (1), so the corners are ``matrix_world @ (+-1, +-1, +-1)``. The box is the
    region to reconstruct."""
    M = np.asarray([list(r) for r in obj.matrix_world], np.float64)
    s = float(getattr(obj, "empty_display_size", 1.0) or 1.0)
    corners = np.array([[x, y, z, 1.0] for x in (-s, s) for y in (-s, s) for z in (-s, s)])
    w = corners @ M.T
    return w[:, :3].min(0), w[:, :3].max(0)


def scene_box(scene):
    """The NeuMesh Box of ``scene`` as the artist left it (moved, rotated, scaled), as the core's object
    box: (centre (3,), half_extents (3,), rotation (3,3) whose columns are the box axes), or None when
    the scene has none (training then finds the box itself). A sheared box (non-uniform scale under a
    rotated parent) is no box: its axis-aligned bounds, which hold all of it, stand in."""
    obj = next((o for o in scene.objects if o.type == "EMPTY" and
                (o.get("neumesh_box_source") is not None or o.name == BOX_NAME)), None)
    if obj is None:
        return None
    M = np.asarray([list(r) for r in obj.matrix_world], np.float64)
    A = M[:3, :3] * float(getattr(obj, "empty_display_size", 1.0) or 1.0)
    half = np.linalg.norm(A, axis=0)
    if not (half > 1e-9).all():
        raise ValueError(f"'{obj.name}' is flat (scale {np.round(half, 6).tolist()}): give it a size on "
                         "every axis, or delete it to let training find the object's box")
    R = A / half
    if not np.allclose(R.T @ R, np.eye(3), atol=1e-4):   # sheared: the bounds of its 8 corners
        lo, hi = box_bounds(obj)
        return (lo + hi) / 2, (hi - lo) / 2, np.eye(3)
    if np.linalg.det(R) < 0:   # a mirrored box: the same box with one axis flipped
        R[:, 2] *= -1
    return M[:3, 3].copy(), half, R


def default_poses_dir(source: str) -> str:
    """Where Poses from Photos writes: beside the photos' folder or the video, '<name>_poses'."""
    src = os.path.normpath(os.path.abspath(source))
    stem = os.path.splitext(os.path.basename(src))[0] if os.path.isfile(src) else os.path.basename(src)
    return os.path.join(os.path.dirname(src), f"{stem or 'capture'}_poses")


# --------------------------------------------------------------------------------------------- the job
class CaptureJob(jobs.Job):
    """Poses (``source`` given: photos folder or video) then read + undistort the capture in ``folder``.
    ``result``: (capture, Ks, photo paths). ``stage``: 'frames', 'extract', 'match', 'map', 'undistort'."""

    def __init__(self, label: str, folder: str, *, source: str = "", fps: float = 2.0, poses_config=None,
                 undistort: bool = True):
        super().__init__(label)
        self.folder, self.source, self.fps = folder, source, float(fps)
        self.poses_config = poses_config
        self.undistort = bool(undistort)
        self.stage = "read"
        self.stages: list = []   # every stage the run went through, in order
        self.registered = 0
        self.report = None
        self.notes: list = []   # the core's warnings while reading the capture (reported, not printed)

    def _part(self, lo, hi, fraction) -> bool:
        return self.progress(lo + (hi - lo) * float(fraction))

    def status_text(self) -> str:
        return f"NeuMesh {self.label}: {self.fraction:.0%} {self.message}".strip()

    def status_lines(self) -> list[str]:
        lines = [f"{self.label.capitalize()}: {self.stage}"]
        if self.message:
            lines.append(self.message)
        if self.registered:
            lines.append(f"{self.registered} photo(s) registered")
        return lines

    def run(self):
        nm = core.get()
        lo = 0.0
        if self.source:
            images, sequential = self.source, False
            if os.path.isfile(self.source):   # a video: its sharpest frames first
                self.stage, self.message = "frames", "reading the video"
                images, sequential = os.path.join(self.folder, "images"), True
                nm.frames_from_video(self.source, images, fps=self.fps,
                                     progress=lambda f: self._part(0.0, 0.1, f))
                lo = 0.1
            cfg = self.poses_config or nm.PosesConfig()
            if cfg.num_threads == -1 and self.threads:
                cfg.num_threads = int(self.threads)

            def on_poses(p):
                self.stage, self.message, self.registered = p.stage, p.message, p.registered
                if not self.stages or self.stages[-1] != p.stage:
                    self.stages.append(p.stage)
                return self._part(lo, 0.9, p.fraction)

            self.report = nm.estimate_poses(images, self.folder, cfg, on_poses, sequential=sequential)
            lo = 0.9
        self.stage, self.message = "read", ""
        with core.CoreNotes() as notes:
            cap = nm.read_capture(self.folder)
        self.notes = list(notes)
        if self.undistort and cap.is_distorted:
            self.stage, self.message = "undistort", f"{len(cap)} photos"
        Ks, paths = nm.undistorted_images(cap, progress=lambda f: self._part(lo, 1.0, f)) if self.undistort \
            else ([lens.K for lens in cap.lenses], list(cap.image_paths))
        self.progress(1.0)
        return cap, Ks, paths


# --------------------------------------------------------------------------------------------- Blender objects
def _collection(scene):
    coll = bpy.data.collections.get(DATASET_COLLECTION)
    if coll is None:
        coll = bpy.data.collections.new(DATASET_COLLECTION)
    if coll.name not in scene.collection.children:
        scene.collection.children.link(coll)
    return coll


def _replace(name):
    old = bpy.data.objects.get(name)
    if old is not None:
        data = old.data
        bpy.data.objects.remove(old, do_unlink=True)
        if data is not None and data.users == 0:
            (bpy.data.meshes if isinstance(data, bpy.types.Mesh) else bpy.data.cameras).remove(data)


def _points_modifier(obj, radius: float):
    """Mesh to Points in a geometry-nodes modifier: loose vertices are not drawn in Object Mode."""
    ng = bpy.data.node_groups.new(POINTS_NAME, "GeometryNodeTree")
    if hasattr(ng, "interface"):   # Blender 4.0+
        ng.interface.new_socket("Geometry", in_out="INPUT", socket_type="NodeSocketGeometry")
        ng.interface.new_socket("Geometry", in_out="OUTPUT", socket_type="NodeSocketGeometry")
    else:
        ng.inputs.new("NodeSocketGeometry", "Geometry")
        ng.outputs.new("NodeSocketGeometry", "Geometry")
    gi, go = ng.nodes.new("NodeGroupInput"), ng.nodes.new("NodeGroupOutput")
    mp = ng.nodes.new("GeometryNodeMeshToPoints")
    mp.inputs["Radius"].default_value = float(radius)
    ng.links.new(gi.outputs[0], mp.inputs["Mesh"])
    ng.links.new(mp.outputs["Points"], go.inputs[0])
    mod = obj.modifiers.new(POINTS_NAME, "NODES")
    mod.node_group = ng
    return mod


def points_object(coll, points, colours, radius: float):
    """The sparse points as a mesh of loose vertices, colours (sRGB uint8) as the point colour
    attribute "Color" (linear float, as Blender stores colours)."""
    _replace(POINTS_NAME)
    pts = np.asarray(points, np.float32).reshape(-1, 3)
    me = bpy.data.meshes.new(POINTS_NAME)
    me.vertices.add(len(pts))
    me.vertices.foreach_set("co", pts.ravel())
    if colours is not None:
        rgba = np.ones((len(pts), 4), np.float32)
        rgba[:, :3] = core.get().srgb_to_linear(np.asarray(colours, np.float32)[:, :3] / 255.0)
        attr = me.color_attributes.new("Color", "FLOAT_COLOR", "POINT")
        attr.data.foreach_set("color", rgba.ravel())
        try:
            me.color_attributes.active_color = attr
        except (AttributeError, TypeError):
            pass
    me.update()
    obj = bpy.data.objects.new(POINTS_NAME, me)
    coll.objects.link(obj)
    try:
        _points_modifier(obj, radius)
    except Exception as exc:  # noqa: BLE001 - the points are still there (Edit Mode shows them)
        print(f"NeuMesh: points drawn as vertices only: {exc}")
    return obj


def box_object(coll, centre, half, source: str):
    """The Empty "NeuMesh Box" (a cube, [-1, 1]^3 scaled by ``half``) around the object region."""
    _replace(BOX_NAME)
    obj = bpy.data.objects.new(BOX_NAME, None)
    obj.empty_display_type = "CUBE"
    obj.empty_display_size = 1.0
    obj.location = [float(v) for v in centre]
    obj.scale = [float(v) for v in half]
    obj["neumesh_box_source"] = source
    coll.objects.link(obj)
    return obj


def held_out_photos(cap) -> list:
    """Indices of the photos of ``cap`` that training holds out for evaluation (the core's rule,
    ``nm.training_photos``: the capture's own split, else every 8th photo)."""
    train = set(core.get().training_photos(cap).names)
    return [i for i, name in enumerate(cap.names) if name not in train]


def held_out_text(cap, held, most: int = 12) -> str:
    """'training holds out 9 of the 67 photos for evaluation: a.jpg, b.jpg, ...' ('' when none)."""
    if not held:
        return "training uses every photo (none is held out)"
    names = [os.path.basename(cap.names[i]) for i in held]
    shown = ", ".join(names[:most]) + (f" and {len(names) - most} more" if len(names) > most else "")
    return (f"training holds out {len(held)} of the {len(cap)} photos for evaluation (their cameras have "
            f"'neumesh_held_out'): {shown}")


def build_capture(context, cap, Ks, paths, max_cameras: int = 0, background_images: bool = True):
    """Cameras, points and box of a capture in the scene. Returns (cameras, points object or None,
    box object or None, warnings). Every photo gets a camera; those training holds out for evaluation
    (:func:`held_out_photos`) carry ``neumesh_held_out`` = True."""
    scene = context.scene
    coll = _collection(scene)
    for o in list(coll.objects):
        if o.type == "CAMERA":
            bpy.data.objects.remove(o, do_unlink=True)
    n = len(cap) if max_cameras <= 0 else min(max_cameras, len(cap))
    warnings, cams, worst = [], [], 0.0
    W, H = cap.lenses[0].width, cap.lenses[0].height
    if any((lens.width, lens.height) != (W, H) for lens in cap.lenses[:n]):
        warnings.append(f"photos of several sizes; the render size is the first's ({W}x{H})")
    scene.render.resolution_x, scene.render.resolution_y = W, H
    scene.render.resolution_percentage = 100
    scene.render.pixel_aspect_x = scene.render.pixel_aspect_y = 1.0
    held = set(held_out_photos(cap))
    for i in range(n):
        lens = cap.lenses[i]
        base = os.path.splitext(os.path.basename(cap.names[i]))[0] or f"{i:04d}"
        cd = bpy.data.cameras.new(f"nm_{base}")
        co = bpy.data.objects.new(f"nm_{i:04d}_{base}"[:63], cd)
        coll.objects.link(co)
        cd.clip_start, cd.clip_end = 0.01, 1000.0
        worst = max(worst, camera.set_camera_from_K(co, Ks[i], cap.c2w[i], lens.width, lens.height))
        co["neumesh_index"] = i
        co["neumesh_photo"] = cap.names[i]
        co["neumesh_held_out"] = i in held
        if background_images:
            try:
                bg = cd.background_images.new()
                bg.image = bpy.data.images.load(paths[i], check_existing=True)
                cd.show_background_images = True
            except Exception as exc:  # noqa: BLE001 - the camera is still useful without its photo
                warnings.append(f"no background photo for {co.name}: {exc}")
        cams.append(co)
    if cams:
        scene.camera = cams[0]
    if worst > 1e-3:
        warnings.append(f"fy differs from fx by {worst:.2%}; Blender cameras use fx")
    box = core.get().capture_object_box(cap)   # the box `neumesh fit` finds for this capture
    box_obj = box_object(coll, box.centre, box.half_extents, box.source)
    pts_obj = None
    if cap.points is not None and len(cap.points):
        radius = 0.004 * float(np.linalg.norm(box.half_extents))
        pts_obj = points_object(coll, cap.points, cap.point_colours, max(radius, 1e-4))
    return cams, pts_obj, box_obj, warnings


# --------------------------------------------------------------------------------------------- operators
def _is_video(path: str) -> bool:
    return os.path.isfile(path) and os.path.splitext(path)[1].lower() in VIDEO_EXTENSIONS


class _CaptureOperator(jobs.JobModal):
    max_cameras: IntProperty(name="Max cameras", default=0, min=0, description="0 = all")
    background_images: BoolProperty(name="Background images", default=True)

    def _finish(self, context, job):
        if job.state == "CANCELLED":
            self.report({"WARNING"}, f"NeuMesh: {self.edit_label} cancelled")
            return {"CANCELLED"}
        if job.state == "ERROR":
            self.report({"ERROR"}, f"NeuMesh: {self.edit_label}: {job.message}")
            return {"CANCELLED"}
        cap, Ks, paths = job.result
        cams, pts, box, warnings = build_capture(context, cap, Ks, paths, self.max_cameras,
                                                 self.background_images)
        context.scene.neumesh.dataset_path = job.folder
        notes = list(getattr(cap, "notes", []) or [])
        for w in list(warnings) + notes + [n for n in job.notes if n not in notes]:
            self.report({"WARNING"}, f"NeuMesh: {w}")
        npts = 0 if pts is None else len(pts.data.vertices)
        self.report({"INFO"}, f"NeuMesh: imported {len(cams)} cameras and {npts} points from {job.folder}; "
                              + held_out_text(cap, held_out_photos(cap)))
        return {"FINISHED"}


class NEUMESH_OT_import_capture(_CaptureOperator, bpy.types.Operator):
    """Import a real capture (a COLMAP folder with sparse/0 and images, or a transforms.json folder) as
    cameras with the photos as backgrounds, its sparse points and a box around the object"""

    bl_idname = "neumesh.import_capture"
    bl_label = "Import capture cameras"
    bl_options = {"REGISTER", "UNDO"}
    edit_label = "importing the capture"

    directory: StringProperty(subtype="DIR_PATH")

    def _start(self, context):
        folder = bpy.path.abspath(self.directory or context.scene.neumesh.dataset_path)
        if not os.path.isdir(folder):
            self.report({"ERROR"}, f"NeuMesh: {folder!r} is not a folder: choose the capture's folder")
            return None
        if os.path.isdir(os.path.join(folder, "sparse")):
            try:
                core.require("capture")   # COLMAP models are read by pycolmap
            except UserError as exc:
                self.report({"ERROR"}, f"NeuMesh: {exc}")
                return None
        return CaptureJob("import", folder, undistort=self.background_images)


class NEUMESH_OT_poses_from_photos(_CaptureOperator, bpy.types.Operator):
    """Estimate the camera poses of a folder of photos or of a video (COLMAP, in the background; Esc
    cancels), then import them as cameras with the sparse points and the object box"""

    bl_idname = "neumesh.poses_from_photos"
    bl_label = "Poses from Photos"
    bl_options = {"REGISTER", "UNDO"}
    edit_label = "estimating poses"

    source: StringProperty(name="Photos or video", subtype="FILE_PATH", default="")
    fps: FloatProperty(name="Frames per second", default=0.0, min=0.0, description="0 = the panel's")
    output: StringProperty(name="Output folder", subtype="DIR_PATH", default="",
                           description="Where the poses go (empty: '<name>_poses' beside the photos)")
    camera_model: StringProperty(default="", description="COLMAP camera model (empty: the core's default)")
    num_features: IntProperty(default=0, min=0, description="SIFT features per photo (0: the core's default)")

    def _start(self, context):
        s = context.scene.neumesh
        src = bpy.path.abspath(self.source or s.capture_source).rstrip("/\\") or ""
        try:
            core.require("capture")
            if not src or not os.path.exists(src):
                raise UserError(f"no photos at {src!r}: choose a folder of photos or a video file")
            if os.path.isfile(src) and not _is_video(src):
                raise UserError(f"{os.path.basename(src)} is not a video ({', '.join(VIDEO_EXTENSIONS)}); "
                                "for photos choose their folder")
            nm = core.get()
        except (UserError, core.CoreUnavailable) as exc:
            self.report({"ERROR"}, f"NeuMesh: {exc}")
            return None
        cfg = nm.PosesConfig()
        if self.camera_model:
            cfg.camera_model = self.camera_model
        if self.num_features:
            cfg.max_num_features = int(self.num_features)
        out = bpy.path.abspath(self.output) if self.output else default_poses_dir(src)
        return CaptureJob("poses", out, source=src, fps=self.fps or s.capture_fps, poses_config=cfg,
                          undistort=self.background_images)


CAPTURE_LABELS = (NEUMESH_OT_poses_from_photos.bl_label, NEUMESH_OT_import_capture.bl_label)


def active_job():
    """The capture job running now (poses or import), or None."""
    for label in CAPTURE_LABELS:
        job = jobs.active(label)
        if job is not None:
            return job
    return None


class NEUMESH_OT_capture_cancel(bpy.types.Operator):
    """Stop estimating poses / importing the capture (nothing is imported)"""

    bl_idname = "neumesh.capture_cancel"
    bl_label = "Cancel"

    def execute(self, context):
        job = active_job()
        if job is None:
            return {"CANCELLED"}
        job.cancel()
        return {"FINISHED"}


classes = (NEUMESH_OT_import_capture, NEUMESH_OT_poses_from_photos, NEUMESH_OT_capture_cancel)
register, unregister = bpy.utils.register_classes_factory(classes)
