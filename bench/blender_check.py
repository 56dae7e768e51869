"""A real BVH client: Blender (PyPI ``bpy``, headless) imports an arm exported by tflearn,
alone and inside the clip's full skeleton; its frame count and the arm bones' world
positions must match tflearn's forward kinematics.

Two steps, two Pythons (bpy is a ~400 MB wheel with its own pins; keep it out of the
project's environment):

    PYTHONPATH=. python bench/blender_check.py prepare DIR [--clip NAME]   # tflearn's venv
    python3.11 -m venv .venv-bpy && .venv-bpy/bin/pip install bpy==4.2.0
    .venv-bpy/bin/python bench/blender_check.py check DIR                   # bpy's venv

``prepare`` imports one clip's right arm, exports it alone as DIR/arm.bvh and writes
DIR/expected.json (frame count, frame time, and per frame the shoulder, elbow, wrist and
hand-tip positions from :func:`tflearn.physics.dynamics.forward_kinematics`, metres, model
world). ``check`` imports DIR/arm.bvh with Blender's BVH importer (global scale 0.01:
centimetres → metres; its default axis conversion, BVH Y up → Blender Z up, turns the
export's world back into the model's) and compares the bones' heads (and the hand's
tail) frame by frame over the imported action's keyframes. ``prepare`` also exports the
arm inside the clip's own full skeleton (:func:`tflearn.mocap.clips.export` with the clip as
``skeleton``) as DIR/full.bvh, prints how far its arm joints lie from the recorded
clip's, and writes DIR/expected_full.json (the shoulder, elbow and wrist joints' world
positions by tflearn's BVH forward kinematics of full.bvh, BVH world, metres);
``check`` imports full.bvh too (global scale: the file's metres per unit; BVH (x, y, z)
lands at Blender (x, −z, y)) and compares those joints' bone heads. For each file it
prints the frame count and the largest difference, and it exits 1 unless the counts
agree and the positions are within 1e-4 m.
"""
from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
BONES = ("upper_arm", "forearm", "hand")


def prepare(out: Path, clip: str) -> None:
    sys.path.insert(0, str(ROOT))
    import numpy as np
    import torch

    from tflearn.mocap import bvh
    from tflearn.mocap import clips as mocap
    from tflearn.mocap import retarget as rt
    from tflearn.physics import dynamics
    folder = Path(os.environ.get("TFLEARN_MOCAP") or ROOT.parent / "shared" / "data" / "mocap")
    frames = rt.arm_frames(bvh.read(folder / f"{clip}.bvh"), "right")
    r = rt.retarget_all([frames])[0]
    t, q = r.motion.t.numpy(), r.motion.q.numpy()
    out.mkdir(parents=True, exist_ok=True)
    bvh.write(rt.arm_skeleton(r.body, t, q), out / "arm.bvh")
    x = dynamics.forward_kinematics(r.body, torch.from_numpy(q)).numpy()
    (out / "expected.json").write_text(json.dumps(
        {"clip": clip, "frames": len(t), "frame_time": float(t[1] - t[0]),
         "positions": x.tolist()}))
    mocap.export(r.body, t, q, out / "full.bvh", skeleton=folder / f"{clip}.bvh")
    full = bvh.read(out / "full.bvh")
    joints = list(rt.find_map(full, "right").names[1:])                 # shoulder, elbow, wrist
    _, xw = full.world()
    _, xc = bvh.read(folder / f"{clip}.bvh").world()             # the recorded arm
    cols = [full.index(j) for j in joints]
    off = float(np.linalg.norm(xw[:, cols] - xc[:, cols], axis=-1).max())
    print(f"full.bvh: its arm joints within {1000 * off:.3f} mm of the recorded clip's")
    (out / "expected_full.json").write_text(json.dumps(
        {"clip": clip, "frames": full.frames, "frame_time": full.frame_time, "scale": full.scale,
         "joints": joints, "positions": xw[:, cols].tolist()}))
    print(f"wrote {out / 'arm.bvh'}, {out / 'full.bvh'} and their expected positions ({len(t)} frames)")


def _blender(path: Path, scale: float):
    """Blender's scene after importing ``path`` (lengths × ``scale``), its armature,
    the first imported frame and the number of frames."""
    import bpy
    bpy.ops.wm.read_factory_settings(use_empty=True)
    bpy.ops.import_anim.bvh(filepath=str(path), global_scale=scale, frame_start=0,
                            use_fps_scale=False, update_scene_fps=True, update_scene_duration=True,
                            rotate_mode="NATIVE")
    obj = next(o for o in bpy.context.scene.objects if o.type == "ARMATURE")
    start, end = obj.animation_data.action.frame_range          # the keyframes imported
    return bpy.context.scene, obj, int(start), int(round(end - start)) + 1


def _compare(path: Path, expected: dict, scale: float, heads: list, tail: str | None,
             world=lambda x: x) -> bool:
    """Frame by frame, the bones' heads (and ``tail``'s tail) against expected
    positions mapped by ``world``; prints the frame count and the largest difference."""
    import bpy
    import numpy as np
    scene, obj, start, n = _blender(path, scale)
    worst = 0.0
    want = world(np.asarray(expected["positions"]))
    for f in range(expected["frames"]):
        scene.frame_set(start + f)
        got = [obj.matrix_world @ obj.pose.bones[b].head for b in heads]
        if tail is not None:
            got.append(obj.matrix_world @ obj.pose.bones[tail].tail)
        worst = max(worst, float(np.abs(np.array([list(v) for v in got]) - want[f]).max()))
    print(f"{path.name}: Blender {bpy.app.version_string}: {n} frames (expected {expected['frames']}), "
          f"fps {scene.render.fps / scene.render.fps_base:.3f} (expected {1 / expected['frame_time']:.3f}); "
          f"largest bone position difference {worst:.2e} m")
    return n == expected["frames"] and worst <= 1e-4


def check(out: Path) -> int:
    arm = json.loads((out / "expected.json").read_text())
    ok = _compare(out / "arm.bvh", arm, 0.01, list(BONES), "hand")
    full = json.loads((out / "expected_full.json").read_text())
    # Blender's default axes: BVH (x, y, z), Y up, lands at (x, −z, y), Z up.
    ok &= _compare(out / "full.bvh", full, full["scale"], full["joints"], None,
                   lambda x: x[..., [0, 2, 1]] * [1, -1, 1])
    return 0 if ok else 1


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("step", choices=("prepare", "check"))
    p.add_argument("dir", type=Path)
    p.add_argument("--clip", default="dataset-2_wave-right-hand_normal_001")
    args = p.parse_args(argv)
    if args.step == "prepare":
        prepare(args.dir, args.clip)
        return 0
    return check(args.dir)


if __name__ == "__main__":
    sys.exit(main())
