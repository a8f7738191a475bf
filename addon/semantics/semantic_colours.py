"""Show semantic colours: the vertex features' first three principal components written as a colour
attribute, so the artist sees what will group together (Solid shading > Attribute)."""
from __future__ import annotations

import bpy

from ..runtime._np import np
from ..runtime import core
from ..runtime.errors import UserError
from ..scene import props
from ..render import field_cache
from .select import core_message

COLOUR_ATTRIBUTE = "NeuMesh semantics"


class NEUMESH_OT_semantic_colours(bpy.types.Operator):
    """Colour the mesh by its semantic features (first three principal components) in a colour
    attribute, to see what will group together (Solid shading > Color: Attribute)"""

    bl_idname = "neumesh.semantic_colours"
    bl_label = "Show semantic colours"
    bl_options = {"REGISTER", "UNDO"}

    def execute(self, context):
        obj = context.active_object
        try:
            core.get()   # the core loads, or the error says what to install
            props.field_path_of(obj)
            field, mesh_index = field_cache.object_field(obj, context.evaluated_depsgraph_get())
            feats = field.vertex_semantics().cpu().numpy().astype(np.float64)
            if mesh_index is not None:   # a remapped mesh: features onto its vertices (others stay 0)
                full = np.zeros((len(obj.data.vertices), feats.shape[1]))
                full[mesh_index] = feats
                feats = full
        except (UserError, core.CoreUnavailable) as exc:
            self.report({"ERROR"}, f"NeuMesh: {exc}")
            return {"CANCELLED"}
        except core.error_types() as exc:
            self.report({"ERROR"}, f"NeuMesh: {core_message(exc, obj)}")
            return {"CANCELLED"}
        if len(obj.data.vertices) != len(feats):
            self.report({"ERROR"}, f"NeuMesh: '{obj.name}' does not have its field's {len(feats)} vertices")
            return {"CANCELLED"}
        rgb = pca_colours(feats)
        me = obj.data
        attr = me.color_attributes.get(COLOUR_ATTRIBUTE)
        if attr is None or attr.domain != "POINT" or attr.data_type != "FLOAT_COLOR":
            if attr is not None:
                me.color_attributes.remove(attr)
            attr = me.color_attributes.new(COLOUR_ATTRIBUTE, "FLOAT_COLOR", "POINT")
        rgba = np.concatenate([rgb, np.ones((len(rgb), 1))], 1).astype(np.float32)
        attr.data.foreach_set("color", rgba.ravel())
        me.color_attributes.active_color = attr
        me.update()
        try:
            for area in context.screen.areas:
                if area.type == "VIEW_3D":
                    area.spaces.active.shading.color_type = "VERTEX"
        except Exception:  # noqa: BLE001 - no screen in background mode
            pass
        self.report({"INFO"}, f"NeuMesh: semantic colours in attribute '{COLOUR_ATTRIBUTE}'")
        return {"FINISHED"}


def pca_colours(feats: np.ndarray) -> np.ndarray:
    """(N,C) features -> (N,3) colours in [0,1]: the first three principal components, each stretched
    between its 1st and 99th percentile."""
    x = feats - feats.mean(0)
    _, _, vt = np.linalg.svd(x[:: max(1, len(x) // 20000)], full_matrices=False)
    y = x @ vt[:3].T
    if y.shape[1] < 3:
        y = np.concatenate([y, np.zeros((len(y), 3 - y.shape[1]))], 1)
    lo, hi = np.percentile(y, 1, axis=0), np.percentile(y, 99, axis=0)
    return np.clip((y - lo) / np.maximum(hi - lo, 1e-9), 0.0, 1.0)


classes = (NEUMESH_OT_semantic_colours,)
register, unregister = bpy.utils.register_classes_factory(classes)
