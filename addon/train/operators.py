"""Operators: import a dataset as cameras, build a scaffold, training (mesh import and field loading:
imports.py)."""
from __future__ import annotations

import os

import bpy
from ..runtime._np import np
from bpy.props import BoolProperty, EnumProperty, IntProperty, StringProperty

from ..runtime import core, jobs
from ..runtime.errors import UserError
from ..runtime.text import text_width, wrapped_label
from ..scene import camera, identity, props, sync
from ..render import field_cache
from ..render.images import DATASET_COLLECTION, dataset_cameras  # noqa: F401 (ui, tests)
from . import capture, worker
from .imports import make_active

def _report_exc(op, exc, what):
    msg = f"NeuMesh: {what}: {exc}" if not isinstance(exc, core.CoreUnavailable) else f"NeuMesh: {exc}"
    op.report({"ERROR"}, msg)
    return {"CANCELLED"}


def _find_image_file(root: str, name: str) -> str | None:
    if not name:
        return None
    cands = [name, os.path.join(root, name)]
    for c in list(cands):
        if not os.path.splitext(c)[1]:
            cands += [c + ".png", c + ".jpg"]
    for c in cands:
        if os.path.isfile(c):
            return os.path.abspath(c)
    return None


def _image_from_array(name: str, img: np.ndarray):
    img = np.asarray(img, np.float32)
    h, w = img.shape[:2]
    rgba = np.ones((h, w, 4), np.float32)
    rgba[..., : min(3, img.shape[2])] = img[..., :3]
    if img.shape[2] == 4:
        rgba[..., 3] = img[..., 3]
    im = bpy.data.images.new(name, w, h, alpha=True)
    im.pixels.foreach_set(np.ascontiguousarray(rgba[::-1]).ravel())
    im.pack()
    return im


def _is_capture(path: str) -> bool:
    """A real capture (COLMAP or transforms.json) as the core detects it: ``nm.read_capture`` reads it
    (cameras only, no pixels); any other folder (NeRF-synthetic, DTU, not a dataset) is not one. A
    folder with sparse/ is one even when pycolmap is missing (Import Cameras then says to install it).
    The core's warnings while reading are dropped here: the import reads the capture again and
    reports them."""
    if os.path.isdir(os.path.join(path, "sparse")):
        return True
    try:
        with core.CoreNotes():
            core.get().read_capture(path)
    except Exception:  # noqa: BLE001 - load_scene below says what is wrong with the folder
        return False
    return True


def looks_like_capture(folder: str) -> bool:
    """What the file browser shows while the artist picks a folder (cheap, no file read): a folder
    with sparse/ (COLMAP) or transforms.json (instant-ngp, nerfstudio) and no NeRF-synthetic split
    files is a capture; :func:`_is_capture` decides on import."""
    if not folder or not os.path.isdir(folder):
        return False
    if os.path.isfile(os.path.join(folder, "transforms_train.json")):
        return False
    return os.path.isdir(os.path.join(folder, "sparse")) or os.path.isfile(os.path.join(folder, "transforms.json"))


def _browsed_folder(context, fallback: str) -> str:
    """The folder the file browser shows now (the operator's ``directory`` is set only on confirm)."""
    params = getattr(getattr(context, "space_data", None), "params", None)
    d = getattr(params, "directory", None)
    if isinstance(d, bytes):
        d = d.decode("utf-8", "replace")
    return bpy.path.abspath(d or fallback or "")


class NEUMESH_OT_import_dataset(bpy.types.Operator):
    """Import a dataset as Blender cameras, each with its photo as camera background image: NeRF-synthetic
    (transforms_*.json), DTU (cameras.npz), or a real capture (COLMAP sparse/0 + images, transforms.json:
    also its sparse points and a box around the object)"""

    bl_idname = "neumesh.import_dataset"
    bl_label = "Import Cameras"   # also the file browser's button: short enough for its default width
    bl_options = {"REGISTER", "UNDO"}

    directory: StringProperty(subtype="DIR_PATH")
    split: EnumProperty(name="Split", items=[("train", "Train", ""), ("val", "Validation", ""), ("test", "Test", "")],
                        default="train", description="Which of the dataset's splits becomes cameras (NeRF-synthetic, "
                                                     "DTU; a capture imports all its photos)")
    downscale: IntProperty(name="Downscale", default=1, min=1, max=16)
    max_cameras: IntProperty(name="Max cameras", default=0, min=0, description="0 = all")
    background_images: BoolProperty(name="Background images", default=True)

    def invoke(self, context, event):
        self._invoked = True
        context.window_manager.fileselect_add(self)
        return {"RUNNING_MODAL"}

    def draw(self, context):
        """The file browser's options: a capture has no split to choose (every photo is imported, and
        the report names those training holds out), so it is not offered there."""
        col = self.layout.column()
        if looks_like_capture(_browsed_folder(context, self.directory)):
            wrapped_label(col, "A capture: every photo becomes a camera. Training holds out every 8th (or "
                               "the capture's own split) for evaluation; the report names them",
                          text_width(context), icon="INFO", context=context)
        else:
            col.prop(self, "split")
            col.prop(self, "downscale")
        col.prop(self, "max_cameras")
        col.prop(self, "background_images")

    def execute(self, context):
        path = bpy.path.abspath(self.directory or context.scene.neumesh.dataset_path)
        if _is_capture(path):   # COLMAP / transforms.json: cameras, photos, points, box in a job
            mode = "INVOKE_DEFAULT" if getattr(self, "_invoked", False) else "EXEC_DEFAULT"
            return bpy.ops.neumesh.import_capture(mode, directory=path, max_cameras=self.max_cameras,
                                                  background_images=self.background_images)
        try:
            nm = core.get()
            with core.CoreNotes() as notes:
                ds = nm.load_scene(path, downscale=self.downscale, background="white")
        except Exception as exc:  # noqa: BLE001
            return _report_exc(self, exc, f"cannot load dataset {path}")
        for note in notes:
            self.report({"WARNING"}, f"NeuMesh: {note}")
        splits = ds.splits
        iset = splits.get(self.split) or splits.get("train") or next(iter(splits.values()))
        cams = iset.cameras
        n = len(cams) if self.max_cameras == 0 else min(self.max_cameras, len(cams))
        scene = context.scene
        coll = bpy.data.collections.get(DATASET_COLLECTION)
        if coll is None:
            coll = bpy.data.collections.new(DATASET_COLLECTION)
        if coll.name not in scene.collection.children:
            scene.collection.children.link(coll)
        for o in list(coll.objects):
            if o.type == "CAMERA":
                bpy.data.objects.remove(o, do_unlink=True)
        W, H = cams.width, cams.height
        scene.render.resolution_x, scene.render.resolution_y = W, H
        scene.render.resolution_percentage = 100
        scene.render.pixel_aspect_x = scene.render.pixel_aspect_y = 1.0
        names = list(getattr(iset, "names", []) or [])
        worst = 0.0
        first = None
        for i in range(n):
            name = os.path.basename(names[i]) if i < len(names) and names[i] else f"{i:04d}"
            cd = bpy.data.cameras.new(f"nm_{self.split}_{name}")
            co = bpy.data.objects.new(f"nm_{self.split}_{i:04d}", cd)
            coll.objects.link(co)
            cd.clip_start, cd.clip_end = 0.01, 1000.0
            worst = max(worst, camera.set_camera_from_K(co, cams.K[i], cams.c2w[i], W, H))
            co["neumesh_index"] = i
            if self.background_images:
                f = _find_image_file(path, names[i] if i < len(names) else "")
                try:
                    im = bpy.data.images.load(f, check_existing=True) if f else \
                        _image_from_array(co.name, iset.float_view(i))
                    bg = cd.background_images.new()
                    bg.image = im
                    cd.show_background_images = True
                except Exception as exc:  # noqa: BLE001 - cameras are still useful without photos
                    self.report({"WARNING"}, f"NeuMesh: no background image for {co.name}: {exc}")
            first = first or co
        if first is not None:
            scene.camera = first
        scene.neumesh.dataset_path = path
        scene.neumesh.downscale = self.downscale
        if worst > 1e-3:
            self.report({"WARNING"}, f"NeuMesh: fy differs from fx by {worst:.2%}; Blender cameras use fx")
        self.report({"INFO"}, f"NeuMesh: imported {n} cameras ({W}x{H}) from {path}")
        return {"FINISHED"}


class NEUMESH_OT_build_scaffold(bpy.types.Operator):
    """Build the scaffold from the dataset's photos: the mesh the field is stored on, each vertex keeping
    the learned codes of the surface around it (visual hull from the masks, refined by stereo or a
    density grid, meshed by marching cubes)"""

    bl_idname = "neumesh.build_scaffold"
    bl_label = "Build scaffold"
    bl_options = {"REGISTER", "UNDO"}

    config_json: StringProperty(default="", options={"HIDDEN", "SKIP_SAVE"},
                                description="JSON object of extra ScaffoldConfig fields (scripts)")

    def execute(self, context):
        s = context.scene.neumesh
        path = bpy.path.abspath(s.dataset_path)
        if not path or not os.path.isdir(path):
            self.report({"ERROR"}, "NeuMesh: set the dataset folder first (Import Cameras)")
            return {"CANCELLED"}
        try:
            nm = core.get()
            core.require("scaffold")
        except (core.CoreUnavailable, UserError) as exc:
            self.report({"ERROR"}, f"NeuMesh: {exc}")
            return {"CANCELLED"}
        build, cfg_cls = nm.build_scaffold, nm.ScaffoldConfig
        wm = context.window_manager
        wm.progress_begin(0, 100)
        try:
            with core.CoreNotes() as notes:
                ds = nm.load_scene(path, downscale=s.downscale, background="white")
            for note in notes:
                self.report({"WARNING"}, f"NeuMesh: {note}")
            box = capture.scene_box(context.scene)   # the NeuMesh Box as the artist left it, if any
            nm.capture_box(ds, None if box is None else nm.ObjectBox(*box))   # the scaffold is built inside

            def prog(*args):  # (stage, fraction)
                frac = [a for a in args if isinstance(a, (int, float))]
                if frac:
                    wm.progress_update(int(100 * float(frac[-1])))
                return True

            known = set(getattr(cfg_cls, "__dataclass_fields__", {}))
            kw = {k: v for k, v in (("method", s.scaffold_method), ("target_vertices", s.scaffold_vertices))
                  if k in known}
            if self.config_json.strip():
                import json

                extra = json.loads(self.config_json)
                unknown = sorted(set(extra) - known)
                if unknown:
                    raise ValueError(f"unknown ScaffoldConfig field(s) {unknown}; known: {sorted(known)}")
                kw.update(extra)
            mesh, report = build(ds, cfg_cls(**kw), prog)
        except Exception as exc:  # noqa: BLE001
            return _report_exc(self, exc, "scaffold failed")
        finally:
            wm.progress_end()
        obj = sync.new_mesh_object("NeuMesh Scaffold", np.asarray(mesh.vertices), np.asarray(mesh.faces))
        make_active(context, obj)
        s.train_object = obj
        secs = getattr(report, "timings", {}).get("total", float("nan")) if report is not None else float("nan")
        self.report({"INFO"}, f"NeuMesh: scaffold with {len(mesh.vertices)} vertices, {len(mesh.faces)} faces "
                              f"({secs:.1f}s)")
        return {"FINISHED"}


def _default_field_path(obj, scene) -> str:
    p = props.field_abspath(obj)
    if p:
        return p
    fname = bpy.path.clean_name(obj.name) + ".neumesh"
    if bpy.data.filepath:
        return os.path.join(os.path.dirname(bpy.data.filepath), fname)
    # an unsaved file: beside the photos, unless that folder is read-only (a shared dataset)
    data = bpy.path.abspath(scene.neumesh.dataset_path)
    folder = data if data and os.path.isdir(data) and os.access(data, os.W_OK) else bpy.app.tempdir
    return os.path.join(folder, fname)


class NEUMESH_OT_train(bpy.types.Operator):
    """Train the NeuMesh field of the mesh object on the dataset in a background thread"""

    bl_idname = "neumesh.train"
    bl_label = "Train field"

    resume: BoolProperty(name="Resume", default=False,
                         description="Continue training the saved field file instead of starting anew")
    wait: BoolProperty(default=False, options={"HIDDEN", "SKIP_SAVE"},
                       description="Block until training ends (scripts, background mode)")
    steps: IntProperty(default=0, min=0, options={"SKIP_SAVE"}, description="0 = scene setting")

    def execute(self, context):
        s = context.scene.neumesh
        obj = s.train_object or context.active_object
        if obj is None or obj.type != "MESH":
            self.report({"ERROR"}, "NeuMesh: choose a mesh object to train (Training > Mesh)")
            return {"CANCELLED"}
        dataset = bpy.path.abspath(s.dataset_path)
        if not dataset or not os.path.isdir(dataset):
            self.report({"ERROR"}, "NeuMesh: set the dataset folder first")
            return {"CANCELLED"}
        job = worker.current()
        if job is not None and job.running:
            self.report({"ERROR"}, "NeuMesh: a training is already running; cancel it first")
            return {"CANCELLED"}
        field_path = _default_field_path(obj, context.scene)
        verts = sync.rest_world_vertices(obj)
        faces = sync.mesh_triangles(obj.data)
        if len(faces) == 0:
            self.report({"ERROR"}, f"NeuMesh: '{obj.name}' has no faces")
            return {"CANCELLED"}
        try:
            job = worker.start(dataset_path=dataset, field_path=field_path, steps=self.steps or s.train_steps,
                               vertices=verts, faces=faces, resume=self.resume, downscale=s.downscale,
                               object_name=obj.name, box=capture.scene_box(context.scene),
                               background_model=s.train_background)
        except Exception as exc:  # noqa: BLE001
            return _report_exc(self, exc, "cannot start training")
        if self.wait:
            job.join()
            jobs.finish(job, _attach_trained)
            if job.state in ("DONE", "CANCELLED"):
                self.report({"INFO"}, job.status_text())
                return {"FINISHED"}
            self.report({"ERROR"}, job.status_text())
            return {"CANCELLED"}
        global _watch
        _watch = jobs.watch(job, _attach_trained)
        self.report({"INFO"}, f"NeuMesh: training '{obj.name}' -> {field_path}")
        return {"FINISHED"}


_watch = None   # the timer following the training (jobs.watch)


def finish_training():
    """Main thread, after the thread ended: attach the saved field to its object (once)."""
    jobs.finish(worker.current(), _attach_trained)


def _attach_trained(job):
    if job.state in ("DONE", "CANCELLED") and os.path.isfile(job.field_path):
        obj = bpy.data.objects.get(job.object_name)
        if obj is not None:
            props.set_field_path(obj, job.field_path)
            try:   # the trained mesh is the field's scaffold: mark its vertices with their ids
                field = field_cache.get_field(obj.name_full, job.field_path)
                if len(obj.data.vertices) == field.num_vertices:
                    identity.attach(bpy.context, obj, field, job.field_path)
            except Exception as exc:  # noqa: BLE001 - the field still renders by vertex order
                print(f"NeuMesh: could not mark the vertices of '{obj.name}': {exc}")


class NEUMESH_OT_train_cancel(bpy.types.Operator):
    """Stop training; the field trained so far is saved (Resume continues from it)"""

    bl_idname = "neumesh.train_cancel"
    bl_label = "Cancel training"

    def execute(self, context):
        job = worker.current()
        if job is None or not job.running:
            self.report({"WARNING"}, "NeuMesh: no training is running")
            return {"CANCELLED"}
        job.cancel()
        self.report({"INFO"}, "NeuMesh: cancelling; the field is saved when the current step ends")
        return {"FINISHED"}


classes = (NEUMESH_OT_import_dataset, NEUMESH_OT_build_scaffold, NEUMESH_OT_train, NEUMESH_OT_train_cancel)


_register_classes, _unregister_classes = bpy.utils.register_classes_factory(classes)


def register():
    _register_classes()


def unregister():
    jobs.stop_timer(_watch)
    job = worker.current()
    if job is not None and job.running:
        job.cancel()
    _unregister_classes()
