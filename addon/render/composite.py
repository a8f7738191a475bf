"""Composite with scene: the NeuMesh fields of a scene rendered by the NEUMESH engine in a companion
scene and Z-combined, in the main scene's compositor, with the main scene's Cycles / EEVEE render.

Blender renders every scene that a Render Layers node of the compositor names, at the main scene's
frame, resolution and render region, so ``blender -b file.blend -a`` renders both engines and combines
them. The field objects stay in the artist's scene, selectable and editable (every edit panel, select
by click and bake keep working there), in a collection "NeuMesh Fields (edit)" whose render visibility
is off (else Cycles would render their scaffold meshes); the companion scene renders the same objects
through its own collection "NeuMesh Fields".  Files set up by earlier versions (the collection
excluded from the main scene's view layers) are changed to this layout when the operator runs again.

Compositor API: Blender 5 keeps the tree in ``scene.compositing_node_group`` (a node group whose
Group Output is the result), earlier versions in ``scene.node_tree`` with a Composite node; the Z
Combine node's options are input sockets in 5 and properties before. Each is chosen by what the
running Blender has, not by its version number.
"""
from __future__ import annotations

import bpy
from bpy.app.handlers import persistent

from ..runtime.errors import UserError
from ..scene import props
from . import colour

FIELDS_COLLECTION = "NeuMesh Fields"            # the companion scene's: renders the fields
EDIT_COLLECTION = "NeuMesh Fields (edit)"       # the artist's scene's: shown and editable, not rendered
NODE_SCENE = "NeuMesh Scene Layer"
NODE_FIELDS = "NeuMesh Field Layer"
NODE_ZCOMBINE = "NeuMesh Z Combine"
NODE_OUTPUT = "NeuMesh Output"
_COPIED = ("resolution_x", "resolution_y", "resolution_percentage", "pixel_aspect_x", "pixel_aspect_y",
           "use_border", "use_crop_to_border", "border_min_x", "border_max_x", "border_min_y", "border_max_y",
           "fps", "fps_base")


def compositor_tree(scene, create: bool = True):
    """The scene's compositing node tree (made when ``create`` and missing), or None."""
    if hasattr(scene, "compositing_node_group"):   # Blender 5: a node group
        tree = scene.compositing_node_group
        if tree is None and create:
            tree = bpy.data.node_groups.new(f"{scene.name} Compositing", "CompositorNodeTree")
            scene.compositing_node_group = tree
        return tree
    if create and not scene.use_nodes:
        scene.use_nodes = True
    return scene.node_tree


def output_input(tree):
    """The input socket whose image becomes the render result: the Group Output's first colour input
    (Blender 5; an "Image" output is added to the group when it has none) or the Composite node's."""
    if not hasattr(bpy.types, "CompositorNodeComposite"):   # Blender 5: the group's output
        if not any(getattr(s, "in_out", "") == "OUTPUT" for s in tree.interface.items_tree):
            tree.interface.new_socket("Image", in_out="OUTPUT", socket_type="NodeSocketColor")
        node = _node(tree, NODE_OUTPUT, "NodeGroupOutput", existing="NodeGroupOutput")
        node.is_active_output = True
        return node.inputs[0]
    node = _node(tree, NODE_OUTPUT, "CompositorNodeComposite", existing="CompositorNodeComposite")
    return node.inputs["Image"]


def _node(tree, name: str, bl_idname: str, existing: str | None = None):
    """The node called ``name`` (or, with ``existing``, the first node of that type), else a new one."""
    node = tree.nodes.get(name)
    if node is None and existing:
        node = next((n for n in tree.nodes if n.bl_idname == existing), None)
    if node is None:
        node = tree.nodes.new(bl_idname)
        node.name = name
    return node


def render_layer_node(tree, name: str, scene, view_layer: str, location):
    node = _node(tree, name, "CompositorNodeRLayers")
    node.scene = scene
    node.layer = view_layer
    node.label = f"{scene.name} / {view_layer}"
    node.location = location
    return node


def to_straight(tree, name: str, image, location):
    """An Alpha Convert node (premultiplied -> straight) on ``image``; its output."""
    node = _node(tree, name, "CompositorNodePremulKey")
    node.location = location
    if hasattr(node, "mapping"):   # before Blender 5: a property
        node.mapping = "PREMUL_TO_STRAIGHT"
    else:                          # Blender 5: a menu input
        node.inputs["Type"].default_value = "To Straight"
    tree.links.new(image, node.inputs[0])
    return node.outputs[0]


def z_combine(tree, front, front_z, back, back_z, location, use_alpha: bool = True):
    """A Z Combine node (named NODE_ZCOMBINE) fed with two images and their depths; its image output.

    With alpha, Z Combine mixes the nearer image over the other by its alpha (``a*near + (1-a)*far``),
    which is "over" for straight colours: the render layers' premultiplied images are converted first
    (else a field's soft edges would darken by a second factor of alpha)."""
    node = _node(tree, NODE_ZCOMBINE, "CompositorNodeZcombine")
    node.location = location
    ins = node.inputs
    x, y = location
    if use_alpha:
        front = to_straight(tree, NODE_ZCOMBINE + " straight A", front, (x - 200, y + 150))
        back = to_straight(tree, NODE_ZCOMBINE + " straight B", back, (x - 200, y - 150))
    for i, src in enumerate((front, front_z, back, back_z)):
        tree.links.new(src, ins[i])
    if hasattr(node, "use_alpha"):   # before Blender 5: properties
        node.use_alpha = use_alpha
        node.use_antialias_z = False
    else:                            # Blender 5: boolean inputs
        for s in ins:
            if s.type == "BOOLEAN":
                s.default_value = use_alpha if s.name == "Use Alpha" else False
    return node.outputs[0]


def field_objects(scene) -> list:
    return [o for o in scene.objects if o.type == "MESH" and props.has_field(o)]


def companion_name(scene) -> str:
    return f"{scene.name} NeuMesh"


def _collection(name: str, parent):
    coll = bpy.data.collections.get(name) or bpy.data.collections.new(name)
    if coll.name not in parent.children:
        parent.children.link(coll)
    return coll


def _fields_collection(scene, companion, objects):
    """The field objects in two collections: FIELDS_COLLECTION in the companion scene (rendered there
    by the NEUMESH engine) and EDIT_COLLECTION in the main scene (visible in its viewport, selectable,
    editable; render visibility off, so Cycles / EEVEE do not render the scaffold meshes).  The objects
    leave the main scene's other collections.  Returns the companion's collection."""
    coll = _collection(FIELDS_COLLECTION, companion.collection)
    if coll.name in scene.collection.children:      # the earlier layout: linked in both, excluded here
        scene.collection.children.unlink(coll)
    coll.hide_render = False
    edit = _collection(EDIT_COLLECTION, scene.collection)
    edit.hide_render = True
    for ob in objects:
        for c in (coll, edit):
            if ob.name not in c.objects:
                c.objects.link(ob)
        for c in list(ob.users_collection):
            if c not in (coll, edit) and (c is scene.collection or c.name in _all_children(scene.collection)):
                c.objects.unlink(ob)
    return coll


def _all_children(coll) -> set:
    out = set()
    for c in coll.children:
        out.add(c.name)
        out |= _all_children(c)
    return out


def sync_companion(scene, companion):
    """Copy what the field render must share with the main scene: camera, resolution and its
    percentage, pixel aspect, render region, frame range and step, frame rate."""
    r, c = scene.render, companion.render
    for name in _COPIED:
        setattr(c, name, getattr(r, name))
    companion.camera = scene.camera
    companion.frame_start, companion.frame_end = scene.frame_start, scene.frame_end
    companion.frame_step = scene.frame_step
    companion.frame_current = scene.frame_current
    companion.neumesh.render_samples = scene.neumesh.render_samples
    companion.neumesh.render_background = scene.neumesh.render_background
    c.film_transparent = True   # alpha = the field's opacity, for the Z Combine's alpha
    if companion.camera is not None and companion.camera.name not in companion.objects:
        companion.collection.objects.link(companion.camera)


def cycles_denoising_check(scene) -> str:
    """Cycles with denoising on fails the render in a build without a denoiser ("Build without
    OpenImageDenoiser": Debian's Blender 3.4, whose Cycles offers no denoiser at all). There denoising is
    switched off; returns what was done ('' when nothing had to be)."""
    cy = getattr(scene, "cycles", None)
    if scene.render.engine != "CYCLES" or cy is None or not getattr(cy, "use_denoising", False):
        return ""
    built = getattr(bpy.app.build_options, "openimagedenoise", None)
    if getattr(cy, "denoiser", "") and built is not False:
        return ""   # a denoiser this build has
    cy.use_denoising = False
    return ("this Blender's Cycles has no denoiser (built without OpenImageDenoise): Render properties > "
            "Sampling > Denoise switched off, else Cycles stops the render")


def set_up(scene) -> dict:
    """Make (or update) the companion scene and the main scene's compositor tree; what was done."""
    if scene.camera is None:
        raise UserError("the scene has no camera: set one (Scene properties > Camera) first")
    objects = field_objects(scene)
    companion = scene.neumesh.composite_scene
    if companion is not None and companion is scene:
        companion = None
    if not objects and companion is not None:
        objects = field_objects(companion)
    if not objects:
        raise UserError("no object with a NeuMesh field in the scene: load one first (Load Field)")
    switched = ""
    if scene.render.engine == "NEUMESH":
        scene.render.engine = "CYCLES"
        switched = "CYCLES"
    if companion is None:
        companion = bpy.data.scenes.get(companion_name(scene)) or bpy.data.scenes.new(companion_name(scene))
        scene.neumesh.composite_scene = companion
    companion.render.engine = "NEUMESH"
    colour.engine_selected(companion)   # its own view never shows; photographic, so its renders don't warn
    denoise = cycles_denoising_check(scene)
    _fields_collection(scene, companion, objects)
    sync_companion(scene, companion)
    for vl in scene.view_layers:
        vl.use_pass_z = True
    for vl in companion.view_layers:
        vl.use_pass_z = True
    tree = compositor_tree(scene)
    main_vl = bpy.context.view_layer.name if bpy.context.scene is scene else scene.view_layers[0].name
    rl_scene = render_layer_node(tree, NODE_SCENE, scene, main_vl, (-400, 200))
    rl_fields = render_layer_node(tree, NODE_FIELDS, companion, companion.view_layers[0].name, (-400, -200))
    image = z_combine(tree, rl_scene.outputs["Image"], rl_scene.outputs["Depth"], rl_fields.outputs["Image"],
                      rl_fields.outputs["Depth"], (0, 0))
    out = output_input(tree)
    out.node.location = (250, 0)
    tree.links.new(image, out)
    scene.render.use_compositing = True
    return {"companion": companion.name, "objects": [o.name for o in objects], "engine": scene.render.engine,
            "denoising": denoise,
            "switched": switched}


class NEUMESH_OT_composite_with_scene(bpy.types.Operator):
    """Render this scene's NeuMesh fields with the NEUMESH engine in a companion scene (same camera,
    frame and resolution) and Z-combine them with this scene's Cycles or EEVEE render in the
    compositor, so fields and ordinary objects occlude each other"""

    bl_idname = "neumesh.composite_with_scene"
    bl_label = "Composite with Scene"
    bl_options = {"REGISTER", "UNDO"}

    def execute(self, context):
        try:
            done = set_up(context.scene)
        except UserError as exc:
            self.report({"ERROR"}, f"NeuMesh: {exc}")
            return {"CANCELLED"}
        msg = (f"NeuMesh: {len(done['objects'])} field object(s) render in scene '{done['companion']}', "
               f"Z-combined with this scene's {done['engine'].replace('BLENDER_', '').title()} render")
        if done["switched"]:
            msg += " (this scene's engine was NeuMesh: now Cycles)"
        if done["denoising"]:
            self.report({"WARNING"}, f"NeuMesh: {done['denoising']}")
        self.report({"INFO"}, msg)
        return {"FINISHED"}


@persistent
def _render_pre(scene, *_args):
    """Before a render of a scene composited with its fields: Cycles without a denoiser renders."""
    try:
        if isinstance(scene, bpy.types.Scene) and scene.neumesh.composite_scene is not None:
            done = cycles_denoising_check(scene)
            if done:
                print(f"NeuMesh: scene '{scene.name}': {done}")
    except Exception as exc:  # noqa: BLE001 - never stop a render over a convenience
        print(f"NeuMesh: {exc}")


classes = (NEUMESH_OT_composite_with_scene,)
_register_classes, _unregister_classes = bpy.utils.register_classes_factory(classes)


def register():
    _register_classes()
    if _render_pre not in bpy.app.handlers.render_pre:
        bpy.app.handlers.render_pre.append(_render_pre)


def unregister():
    if _render_pre in bpy.app.handlers.render_pre:
        bpy.app.handlers.render_pre.remove(_render_pre)
    _unregister_classes()
