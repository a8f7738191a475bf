"""Scene building helpers shared by the Blender tests (and the real-Blender driver script)."""
from __future__ import annotations

import math

import numpy as np


def grid_mesh(nx=12, ny=4, size=(1.2, 0.4), z=0.0):
    """A flat (nx*ny vertex) grid along x, triangulated; returns (V,3) float32, (F,3) int64."""
    xs = np.linspace(-size[0] / 2, size[0] / 2, nx)
    ys = np.linspace(-size[1] / 2, size[1] / 2, ny)
    X, Y = np.meshgrid(xs, ys, indexing="xy")
    V = np.stack([X.ravel(), Y.ravel(), np.full(X.size, z)], -1).astype(np.float32)
    F = []
    for j in range(ny - 1):
        for i in range(nx - 1):
            a = j * nx + i
            F += [(a, a + 1, a + nx + 1), (a, a + nx + 1, a + nx)]
    return V, np.asarray(F, np.int64)


def add_armature_bend(obj, split_x=0.0, angle_deg=60.0, axis="Y", frame=None):
    """Rig ``obj`` with a two-bone armature along x; vertices with x > split_x follow the second bone,
    which is rotated by ``angle_deg`` (keyed at ``frame`` if given). Returns the armature object."""
    import bpy

    me = obj.data
    xs = np.array([v.co.x for v in me.vertices])
    x0, x1 = float(xs.min()), float(xs.max())
    arm_data = bpy.data.armatures.new("rig")
    arm = bpy.data.objects.new("rig", arm_data)
    bpy.context.scene.collection.objects.link(arm)
    arm.matrix_world = obj.matrix_world.copy()
    bpy.context.view_layer.objects.active = arm
    bpy.ops.object.mode_set(mode="EDIT")
    b1 = arm_data.edit_bones.new("root")
    b1.head, b1.tail = (x0, 0, 0), (split_x, 0, 0)
    b2 = arm_data.edit_bones.new("tip")
    b2.head, b2.tail = (split_x, 0, 0), (x1, 0, 0)
    b2.parent = b1
    b2.use_connect = True
    bpy.ops.object.mode_set(mode="OBJECT")
    g_root = obj.vertex_groups.new(name="root")
    g_tip = obj.vertex_groups.new(name="tip")
    idx_tip = [v.index for v in me.vertices if v.co.x > split_x]
    idx_root = [v.index for v in me.vertices if v.co.x <= split_x]
    g_tip.add(idx_tip, 1.0, "REPLACE")
    g_root.add(idx_root, 1.0, "REPLACE")
    mod = obj.modifiers.new("Armature", "ARMATURE")
    mod.object = arm
    pb = arm.pose.bones["tip"]
    pb.rotation_mode = "XYZ"
    rot = [0.0, 0.0, 0.0]
    rot["XYZ".index(axis)] = math.radians(angle_deg)
    if frame is None:
        pb.rotation_euler = rot
    else:
        pb.rotation_euler = (0, 0, 0)
        pb.keyframe_insert("rotation_euler", frame=frame[0])
        pb.rotation_euler = rot
        pb.keyframe_insert("rotation_euler", frame=frame[1])
    bpy.context.view_layer.objects.active = obj
    bpy.context.view_layer.update()
    return arm, np.asarray(idx_root), np.asarray(idx_tip)


def careless_cap_pairs(obj):
    """Vertex groups "cap+" / "cap-" (the blob's caps along x) and four pairs that squeeze the cap+
    source onto a few neighbouring vertices of cap- (as a careless pick would), selected in edit-mode
    history order: a source vertex, then its target.  Runs in bpy 5 and in Blender 3.4."""
    import bmesh

    co = np.array([v.co[:] for v in obj.data.vertices])
    c = co - co.mean(0)
    src, tgt = np.nonzero(c[:, 0] > 0.3)[0], np.nonzero(c[:, 0] < -0.3)[0]
    for name, idx in (("cap+", src), ("cap-", tgt)):
        obj.vertex_groups.new(name=name).add([int(i) for i in idx], 1.0, "REPLACE")
    s_pick = [src[np.argmax(c[src, 1])], src[np.argmin(c[src, 1])], src[np.argmax(c[src, 2])],
              src[np.argmin(c[src, 2])]]
    centre = tgt[np.argmin(c[tgt, 0])]
    t_pick = tgt[np.argsort(np.linalg.norm(c[tgt] - c[centre], axis=1))[:4]]
    bm = bmesh.new()
    bm.from_mesh(obj.data)
    bm.verts.ensure_lookup_table()
    for v in bm.verts:
        v.select = False
    for s_i, t_i in zip(s_pick, t_pick):
        for i in (s_i, t_i):
            bm.verts[int(i)].select = True
            bm.select_history.add(bm.verts[int(i)])
    bm.to_mesh(obj.data)
    bm.free()


def add_camera(location, look_at=(0, 0, 0), lens=35.0, name="cam"):
    import bpy
    import mathutils

    cd = bpy.data.cameras.new(name)
    cd.lens = lens
    cd.sensor_fit = "AUTO"
    cd.sensor_width = 36.0
    co = bpy.data.objects.new(name, cd)
    bpy.context.scene.collection.objects.link(co)
    loc = mathutils.Vector(location)
    direction = mathutils.Vector(look_at) - loc
    co.matrix_world = mathutils.Matrix.Translation(loc) @ direction.to_track_quat("-Z", "Y").to_matrix().to_4x4()
    bpy.context.scene.camera = co
    return co


def field_in_camera(field_path, width, height):
    """Load ``field_path`` as a new object, seen by a camera in front of it, rendered by NEUMESH at
    ``width`` x ``height`` with exact colours (:func:`exact_colour_settings`); returns the object."""
    import bpy

    assert bpy.ops.neumesh.load_field(filepath=field_path, new_object=True) == {"FINISHED"}
    obj = bpy.context.active_object
    add_camera((0.0, -4.8, 0.6), lens=35.0)
    scene = bpy.context.scene
    scene.render.engine = "NEUMESH"
    exact_colour_settings(scene, width, height)
    bpy.context.view_layer.update()
    return obj


def manual_K_c2w(cam_obj, width, height):
    """Independent K / OpenCV c2w from lens & sensor (sensor_fit AUTO, no shift) for checking."""
    cd = cam_obj.data
    f = cd.lens / cd.sensor_width * max(width, height)
    K = np.array([[f, 0, width / 2], [0, f, height / 2], [0, 0, 1]], np.float32)
    M = np.array([list(r) for r in cam_obj.matrix_world], np.float64)
    c2w = (M @ np.diag([1.0, -1.0, -1.0, 1.0])).astype(np.float32)
    return K, c2w


def exact_colour_settings(scene, width, height, filepath=None, depth="16"):
    scene.render.resolution_x, scene.render.resolution_y = width, height
    scene.render.resolution_percentage = 100
    scene.view_settings.view_transform = "Standard"
    scene.view_settings.look = "None"
    scene.view_settings.exposure = 0.0
    scene.view_settings.gamma = 1.0
    scene.display_settings.display_device = "sRGB"
    scene.render.dither_intensity = 0.0
    scene.render.image_settings.file_format = "PNG"
    scene.render.image_settings.color_mode = "RGBA"
    scene.render.image_settings.color_depth = depth
    if filepath:
        scene.render.filepath = filepath


def read_exr(path):
    """(H,W,4) float32 pixels of an image file, top row first, through bpy (scene linear for EXR)."""
    import bpy

    img = bpy.data.images.load(path)
    try:
        w, h = img.size
        px = np.empty(w * h * 4, np.float32)
        img.pixels.foreach_get(px)
        return px.reshape(h, w, 4)[::-1].copy()
    finally:
        bpy.data.images.remove(img)


def linear_to_srgb(x):
    x = np.clip(x, 0, None)
    return np.where(x <= 0.0031308, x * 12.92, 1.055 * np.power(x, 1 / 2.4) - 0.055)


def f12_srgb(path):
    """Render the scene (F12) to a 32-bit EXR at ``path`` and return (H,W,3) display-referred sRGB,
    comparable with ``nm.render_camera(...).rgb`` (the engine decodes to scene linear for Blender)."""
    import bpy

    scene = bpy.context.scene
    scene.render.image_settings.file_format = "OPEN_EXR"
    scene.render.image_settings.color_depth = "32"
    scene.render.filepath = str(path)
    bpy.ops.render.render(write_still=True)
    return linear_to_srgb(read_exr(str(path))[..., :3])


def render_pass(composite, scene, socket, path, view_layer=None):
    """(H,W,4) float32 pixels of one output (``socket``: "Image", "Alpha", "Depth", "NeuMesh Mod") of
    ``scene``'s Render Layers, top row first: a probe scene's compositor (``composite``: the add-on's
    composite module) routes it to its result, written as a 32-bit EXR at ``path`` (the probe's own
    layers are not rendered: no Render Layers node names it)."""
    import bpy

    probe = bpy.data.scenes.new("probe")
    try:
        for name in ("resolution_x", "resolution_y", "resolution_percentage", "use_border", "use_crop_to_border",
                     "border_min_x", "border_max_x", "border_min_y", "border_max_y"):
            setattr(probe.render, name, getattr(scene.render, name))
        probe.camera = scene.camera
        probe.frame_current = scene.frame_current
        probe.render.engine = scene.render.engine
        tree = composite.compositor_tree(probe)
        rl = composite.render_layer_node(tree, "probe layer", scene, view_layer or scene.view_layers[0].name, (0, 0))
        tree.links.new(rl.outputs[socket], composite.output_input(tree))
        probe.render.image_settings.file_format = "OPEN_EXR"
        probe.render.image_settings.color_depth = "32"
        probe.render.filepath = str(path)
        bpy.ops.render.render(write_still=True, scene=probe.name)
        return read_exr(str(path))
    finally:
        tree = composite.compositor_tree(probe, create=False)
        group = tree.name if tree is not None and bpy.data.node_groups.get(tree.name) == tree else None
        bpy.data.scenes.remove(probe)   # a node group (Blender 5) outlives its scene: removed too
        if group is not None:
            bpy.data.node_groups.remove(bpy.data.node_groups[group])


def cycles_fast(scene, samples=4):
    """Tiny, quick, deterministic Cycles settings for tests (CPU, no denoising, narrow pixel filter)."""
    scene.render.engine = "CYCLES"
    c = scene.cycles
    c.device = "CPU"
    c.samples = samples
    c.use_denoising = False
    if hasattr(c, "use_adaptive_sampling"):
        c.use_adaptive_sampling = False
    c.filter_width = 0.01
    c.seed = 0
    c.max_bounces = 2


def bar_through_field(length=2.6, angle_deg=35.0):
    """A long Cycles box through the field, its left end nearer the camera than the field and its
    right end farther (camera on -y looking at the origin), lit by a sun."""
    import bpy

    bpy.ops.mesh.primitive_cube_add(size=1.0, location=(0.0, 0.0, 0.15), rotation=(0, 0, math.radians(angle_deg)))
    bar = bpy.context.active_object
    bar.name = "bar"
    bar.scale = (length, 0.25, 0.25)
    mat = bpy.data.materials.new("bar red")
    mat.diffuse_color = (0.8, 0.1, 0.05, 1.0)
    if mat.node_tree is None:   # Blender < 5 makes materials without nodes
        mat.use_nodes = True
    if mat.node_tree is not None:
        bsdf = mat.node_tree.nodes.get("Principled BSDF")
        if bsdf is not None:
            bsdf.inputs["Base Color"].default_value = (0.8, 0.1, 0.05, 1.0)
    bar.data.materials.append(mat)
    sun = bpy.data.objects.new("sun", bpy.data.lights.new("sun", "SUN"))
    sun.data.energy = 3.0
    sun.rotation_euler = (math.radians(40), 0, math.radians(20))
    bpy.context.scene.collection.objects.link(sun)
    return bar


def straight(img):
    a = img[..., 3:4]
    return np.concatenate([np.where(a > 0, img[..., :3] / np.maximum(a, 1e-12), img[..., :3]), a], -1)


def combine_expected(cyc, zc, fld, zf):
    """What the set-up's Z Combine makes of two premultiplied layers: the nearer one over the other
    (colours made straight, then mixed by the nearer one's alpha), alpha the larger of the two."""
    front_is_field = (zf < zc)[..., None]
    fg, bg = np.where(front_is_field, fld, cyc), np.where(front_is_field, cyc, fld)
    a = fg[..., 3:4]
    out = straight(fg) * a + straight(bg) * (1 - a)
    out[..., 3] = np.maximum(fg[..., 3], bg[..., 3])
    return out


class Recorder:
    """A stand-in for a panel's ``layout``: records every label's text, every operator's idname and the
    context pointers set (rows, columns, boxes and splits record into the same lists), so a test can
    read what a panel draws without a window.  ``draw_panel(cls, context)`` runs ``cls.draw`` on one."""

    def __init__(self, labels=None, operators=None, buttons=None, parent=None, props=None):
        self.labels = [] if labels is None else labels
        self.operators = [] if operators is None else operators
        self.buttons = [] if buttons is None else buttons   # (idname, text, the layout it is in)
        self.props = [] if props is None else props         # the property names drawn
        self.parent = parent
        self.enabled = True
        self.alert = False
        self.scale_y = 1.0
        self.active = True
        self.use_property_split = False
        self.use_property_decorate = False
        self.pointers = {}

    def _child(self, *a, **k):
        child = Recorder(self.labels, self.operators, self.buttons, self, self.props)
        child.pointers = self.pointers
        return child

    def context_pointer_set(self, name, value):
        self.pointers[name] = value

    column = row = box = split = column_flow = grid_flow = _child

    def label(self, text="", **k):
        self.labels.append(text)

    def operator(self, idname, text="", **k):
        self.operators.append(idname)
        self.buttons.append((idname, text, self))
        import types
        return types.SimpleNamespace()

    def is_enabled(self) -> bool:
        """Enabled as Blender draws it: this layout and every layout it is in."""
        return self.enabled and (self.parent is None or self.parent.is_enabled())

    def button(self, idname):
        """(text, enabled) of the last button of operator ``idname`` (KeyError when none was drawn)."""
        for name, text, layout in reversed(self.buttons):
            if name == idname:
                return text, layout.is_enabled()
        raise KeyError(idname)

    def prop(self, *a, **k):
        if len(a) > 1:
            self.props.append(a[1])

    prop_search = prop

    def separator(self, *a, **k):
        pass

    progress = template_list = prop_enum = menu = popover = separator

    @property
    def text(self):
        return " ".join(self.labels)


def draw_panel(cls, context, rec=None):
    """(labels, operator idnames) that panel class ``cls`` draws in ``context`` (into ``rec``, a
    :class:`Recorder`, when given: its ``pointers`` are the context pointers the panel set)."""
    rec = record_panel(cls, context, rec)
    return rec.labels, rec.operators


def record_panel(cls, context, rec=None) -> Recorder:
    """The :class:`Recorder` panel class ``cls`` drew into in ``context`` (labels, buttons and whether
    each is enabled, context pointers); a new one unless ``rec`` is given."""
    import types

    rec = Recorder() if rec is None else rec

    class _Panel:   # the panel's methods bound to a stand-in with a recording layout
        layout = rec

        def __getattr__(self, name):
            value = getattr(cls, name)
            return types.MethodType(value, self) if isinstance(value, types.FunctionType) else value

    cls.draw(_Panel(), context)
    return rec
