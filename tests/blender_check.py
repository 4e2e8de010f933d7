"""Run inside Blender's Python (the `bpy` module): import our .glb and .bvh with Blender's own importers.

    python blender_check.py --glb a.glb --bvh a.bvh --bvh-scale 0.01 --fps 30 \
        --frames 0,15,40 --bones left_wrist,right_wrist --out result.json [--render picture.png]

Writes JSON: {"version": ..., "glb": {bone: [[x, y, z] per frame]}, "bvh": {...}} with the
bones' head positions in the project's world (y up, metres), read after Blender has played
the animation to each frame. Imports only bpy and the standard library, so it runs in an
environment of its own (bpy pins numpy < 2).
"""
from __future__ import annotations

import argparse
import json

import bpy
from mathutils import Vector


def _armature(before):
    new = [o for o in bpy.context.scene.objects if o.name not in before and o.type == "ARMATURE"]
    if len(new) != 1:
        raise SystemExit(f"expected one imported armature; got {[o.name for o in new]}")
    return new[0]


def _sample(arm, bones, frames, first_frame):
    out = {b: [] for b in bones}
    for f in frames:
        bpy.context.scene.frame_set(first_frame + f)
        bpy.context.view_layer.update()
        for b in bones:
            pb = arm.pose.bones.get(b)
            if pb is None:
                raise SystemExit(f"bone {b!r} not in {arm.name}: {[p.name for p in arm.pose.bones][:80]}")
            p = arm.matrix_world @ pb.head
            # Blender is z up (its importers turn y-up files so): back to the project's y up
            out[b].append([p.x, p.z, -p.y])
    return out


def _mesh_vertices(mesh):
    dg = bpy.context.evaluated_depsgraph_get()
    ev = mesh.evaluated_get(dg)
    m = ev.to_mesh()
    out = [mesh.matrix_world @ v.co for v in m.vertices]
    ev.to_mesh_clear()
    return out


def _swap_mesh(glb_arm, bvh_arm, frames):
    """Largest vertex distance (m) between the .glb mesh under its own armature and under the BVH armature."""
    meshes = [o for o in bpy.context.scene.objects if o.type == "MESH" and any(
        m.type == "ARMATURE" and m.object == glb_arm for m in o.modifiers)]
    if len(meshes) != 1:
        raise SystemExit(f"expected one mesh skinned to {glb_arm.name}; got {[o.name for o in meshes]}")
    mesh = meshes[0]
    mod = next(m for m in mesh.modifiers if m.type == "ARMATURE")
    worst = 0.0
    for f in frames:
        bpy.context.scene.frame_set(f)
        a = _mesh_vertices(mesh)
        mod.object = bvh_arm
        bpy.context.scene.frame_set(f + 1)  # the BVH was keyed from frame 1
        b = _mesh_vertices(mesh)
        mod.object = glb_arm
        worst = max(worst, max((u - v).length for u, v in zip(a, b)))
    return worst


def _render(path, target):
    scene = bpy.context.scene
    scene.render.engine = "BLENDER_WORKBENCH"
    scene.display.shading.light = "STUDIO"
    scene.display.shading.color_type = "MATERIAL"
    scene.display.shading.show_shadows = True
    scene.render.resolution_x, scene.render.resolution_y = 640, 640
    scene.render.film_transparent = False
    scene.world = scene.world or bpy.data.worlds.new("world")
    bpy.ops.mesh.primitive_plane_add(size=4.0, location=(0.0, 0.0, 0.0))
    cam_data = bpy.data.cameras.new("camera")
    cam_data.lens = 50
    cam = bpy.data.objects.new("camera", cam_data)
    scene.collection.objects.link(cam)
    # in front of the figure (it faces -y in Blender), a little to its left and above
    cam.location = Vector((target.x + 1.2, target.y - 3.6, target.z + 0.5))
    direction = target - cam.location
    cam.rotation_euler = direction.to_track_quat("-Z", "Y").to_euler()
    scene.camera = cam
    scene.render.filepath = path
    bpy.ops.render.render(write_still=True)


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--glb")
    ap.add_argument("--bvh")
    ap.add_argument("--bvh-scale", type=float, default=1.0)
    ap.add_argument("--fps", type=float, required=True)
    ap.add_argument("--frames", required=True)
    ap.add_argument("--bones", required=True)
    ap.add_argument("--out", required=True)
    ap.add_argument("--render", default=None)
    ap.add_argument("--render-frame", type=int, default=0)
    args = ap.parse_args()
    frames = [int(x) for x in args.frames.split(",")]
    bones = args.bones.split(",")

    bpy.ops.wm.read_factory_settings(use_empty=True)
    scene = bpy.context.scene
    # whole frame rates only (30, 60): Blender's fps is an int over fps_base
    scene.render.fps = int(round(args.fps))
    scene.render.fps_base = scene.render.fps / args.fps
    result = {"version": bpy.app.version_string}

    if args.bvh:
        before = {o.name for o in scene.objects}
        bpy.ops.import_anim.bvh(filepath=args.bvh, global_scale=args.bvh_scale, frame_start=1,
                                use_fps_scale=False, update_scene_fps=False, update_scene_duration=True,
                                rotate_mode="NATIVE", axis_forward="-Z", axis_up="Y")
        arm = _armature(before)
        # the BVH importer keys file frame i at Blender frame frame_start + i
        result["bvh"] = _sample(arm, bones, frames, 1)
        bvh_arm = arm

    if args.glb:
        before = {o.name for o in scene.objects}
        bpy.ops.import_scene.gltf(filepath=args.glb)
        arm = _armature(before)
        # the glTF importer keys time t at frame t * fps (time 0 at frame 0)
        result["glb"] = _sample(arm, bones, frames, 0)
        if args.bvh:
            # docs/blender.md step 4: a mesh bound to the rig, driven by the imported BVH armature
            # through its Armature modifier, deforms as under the glTF armature it came with
            result["mesh_swap_max_m"] = _swap_mesh(arm, bvh_arm, frames)
            bvh_arm.hide_set(True)
            bvh_arm.hide_render = True
        if args.render:
            scene.frame_set(args.render_frame)
            bpy.context.view_layer.update()
            hips = arm.matrix_world @ arm.pose.bones[0].head
            _render(args.render, Vector((hips.x, hips.y, max(hips.z, 0.9))))
            result["render"] = args.render

    with open(args.out, "w") as f:
        json.dump(result, f)


if __name__ == "__main__":
    main()
