"""Render a baked asset with Cycles inside Blender (``blender -b --python`` this file ``-- JOB.npz OUT_DIR``).

Run by ``bench_bake.py --cycles``; needs only Blender and numpy (no torch; folders in the environment
variable NEUMESH_PYTHONPATH go on sys.path first, e.g. the add-on's ``.blender_torch``).  ``JOB.npz`` holds the
baked mesh (vertices, faces, uvs), the texture's PNG path, the cameras (K (n,3,3), c2w (n,4,4) OpenCV,
width, height), the background colour, samples and threads.  The object gets the add-on's *Emission*
material (Principled BSDF: texture as emission at strength 1, black base colour, specular 0) and the
world the background colour; view transform Standard, so a pixel shows the texture's sRGB value.
Writes OUT_DIR/cycles_<i>.png and OUT_DIR/cycles.json (seconds per view).
"""
import json
import os
import sys
import time

import bpy
from mathutils import Matrix

# Blender's own Python may lack numpy: the folders in NEUMESH_PYTHONPATH (e.g. .blender_torch) come first
for _p in reversed([p for p in os.environ.get("NEUMESH_PYTHONPATH", "").split(os.pathsep) if p]):
    sys.path.insert(0, _p)
import numpy as np  # noqa: E402


def main(job_path, out_dir):
    job = np.load(job_path, allow_pickle=False)
    bpy.ops.wm.read_factory_settings(use_empty=True)
    scene = bpy.context.scene
    v = job["vertices"].astype(np.float32)
    f = job["faces"].astype(np.int32)
    uv = job["uvs"].astype(np.float32)
    me = bpy.data.meshes.new("baked")
    me.vertices.add(len(v))
    me.vertices.foreach_set("co", v.ravel())
    me.loops.add(f.size)
    me.loops.foreach_set("vertex_index", f.ravel())
    me.polygons.add(len(f))
    me.polygons.foreach_set("loop_start", np.arange(0, f.size, 3, dtype=np.int32))
    if bpy.app.version < (3, 6, 0):
        me.polygons.foreach_set("loop_total", np.full(len(f), 3, dtype=np.int32))
    me.update(calc_edges=True)
    layer = me.uv_layers.new(name="NeuMesh bake")
    layer.data.foreach_set("uv", uv[f].ravel())
    obj = bpy.data.objects.new("baked", me)
    scene.collection.objects.link(obj)

    mat = bpy.data.materials.new("baked")
    mat.use_nodes = True
    nodes, links = mat.node_tree.nodes, mat.node_tree.links
    bsdf = next(n for n in nodes if n.type == "BSDF_PRINCIPLED")
    tex = nodes.new("ShaderNodeTexImage")
    tex.image = bpy.data.images.load(str(job["texture_path"]))
    tex.interpolation = "Linear"
    uvn = nodes.new("ShaderNodeUVMap")
    uvn.uv_map = "NeuMesh bake"
    links.new(uvn.outputs["UV"], tex.inputs["Vector"])
    emission = bsdf.inputs["Emission Color"] if "Emission Color" in bsdf.inputs else bsdf.inputs["Emission"]
    links.new(tex.outputs["Color"], emission)
    bsdf.inputs["Emission Strength"].default_value = 1.0
    bsdf.inputs["Base Color"].default_value = (0, 0, 0, 1)
    spec = "Specular IOR Level" if "Specular IOR Level" in bsdf.inputs else "Specular"
    bsdf.inputs[spec].default_value = 0.0
    bsdf.inputs["Roughness"].default_value = 1.0
    me.materials.append(mat)

    world = bpy.data.worlds.new("bg")
    world.use_nodes = True
    bg = world.node_tree.nodes["Background"]
    col = [float(c) for c in job["background"]]
    # the world is seen directly: its colour is scene-linear, the background colour display (sRGB) values
    lin = [c / 12.92 if c <= 0.04045 else ((c + 0.055) / 1.055) ** 2.4 for c in col]
    bg.inputs["Color"].default_value = (*lin, 1.0)
    bg.inputs["Strength"].default_value = 1.0
    scene.world = world

    scene.render.engine = "CYCLES"
    scene.cycles.device = "CPU"
    scene.cycles.samples = int(job["samples"])
    scene.cycles.use_denoising = False
    scene.cycles.max_bounces = 0          # emission seen directly; nothing to bounce
    scene.render.threads_mode = "FIXED"
    scene.render.threads = int(job["threads"])
    scene.render.film_transparent = False
    scene.view_settings.view_transform = "Standard"
    scene.view_settings.look = "None"
    scene.render.resolution_x = int(job["width"])
    scene.render.resolution_y = int(job["height"])
    scene.render.resolution_percentage = 100
    scene.render.image_settings.file_format = "PNG"
    scene.render.image_settings.color_mode = "RGB"

    cam_data = bpy.data.cameras.new("cam")
    cam = bpy.data.objects.new("cam", cam_data)
    scene.collection.objects.link(cam)
    scene.camera = cam
    W, H = int(job["width"]), int(job["height"])
    times = []
    for i, (K, c2w) in enumerate(zip(job["K"], job["c2w"])):
        cam_data.sensor_fit = "HORIZONTAL"
        cam_data.sensor_width = 36.0
        cam_data.lens = float(K[0, 0]) * 36.0 / W
        cam_data.shift_x = -(float(K[0, 2]) - W / 2) / W
        cam_data.shift_y = (float(K[1, 2]) - H / 2) / W
        gl = np.asarray(c2w, np.float64) @ np.diag([1.0, -1.0, -1.0, 1.0])   # OpenCV -> Blender camera
        cam.matrix_world = Matrix([list(map(float, r)) for r in gl])   # rows (a plain list is read by columns)
        scene.render.filepath = os.path.join(out_dir, f"cycles_{i}.png")
        t0 = time.perf_counter()
        bpy.ops.render.render(write_still=True)
        times.append(time.perf_counter() - t0)
    with open(os.path.join(out_dir, "cycles.json"), "w") as fh:
        json.dump({"seconds_per_view": times, "blender": bpy.app.version_string}, fh)


if __name__ == "__main__":
    argv = sys.argv[sys.argv.index("--") + 1:]
    main(argv[0], argv[1])
