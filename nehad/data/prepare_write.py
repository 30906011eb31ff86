"""The last steps of `nehad prepare` (:mod:`nehad.data.prepare`): the posed cameras from the
reconstruction (:func:`camera_poses_of`, with the registration rules) and the scene folder in the
D-NeRF layout (:func:`write_scene`).

Conventions: COLMAP's cameras are OpenCV (x right, y down, z forward) with pixel centres at
i + 0.5, as the project's (docs/design.md section 3), so principal points carry over unchanged;
the transforms files hold camera-to-world in OpenGL axes (y up, z back), as D-NeRF's.
"""

from __future__ import annotations

import json
import shutil

import numpy as np

from nehad.data.capture_inputs import PrepareError
from nehad.data.common import points_ply_bytes, undistortion_maps
from nehad.data.sfm import CameraPose, normalisation, poses, sparse_points
from nehad.runtime.images import atomic_write_bytes

__all__ = ["camera_poses_of", "write_scene", "pinhole"]

#: COLMAP camera models `nehad prepare` accepts, and their parameter order.
CAMERA_MODELS = {
    "SIMPLE_PINHOLE": ("f", "cx", "cy"),
    "PINHOLE": ("fx", "fy", "cx", "cy"),
    "SIMPLE_RADIAL": ("f", "cx", "cy", "k1"),
    "RADIAL": ("f", "cx", "cy", "k1", "k2"),
    "OPENCV": ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2"),
}


def pinhole(model: str, params) -> tuple[tuple[float, float, float, float], tuple, tuple]:
    """((fx, fy, cx, cy), (k1, k2, k3), (p1, p2)) of a COLMAP camera."""
    v = dict(zip(CAMERA_MODELS[model], params))
    fx = v.get("fx", v.get("f"))
    fy = v.get("fy", v.get("f"))
    return ((fx, fy, v["cx"], v["cy"]), (v.get("k1", 0.0), v.get("k2", 0.0), 0.0),
            (v.get("p1", 0.0), v.get("p2", 0.0)))


def _mean_pose(items: list[CameraPose]) -> CameraPose:
    """One pose from the same camera registered at several instants: the mean centre, the
    rotation nearest the mean rotation matrix (chordal mean), the mean intrinsics."""
    u, _, vt = np.linalg.svd(sum(p.rotation for p in items))
    rot = u @ np.diag([1.0, 1.0, np.linalg.det(u @ vt)]) @ vt
    first = items[0]
    return CameraPose(rot, np.mean([p.centre for p in items], axis=0), first.model,
                      tuple(np.mean([p.params for p in items], axis=0)), first.width, first.height)


def _required(run, total: int) -> int:
    need = run.options.min_registered
    return total if need is None else min(int(need), total)


def camera_poses_of(run, model, chosen: dict, check=None) -> dict:
    """Rig: camera name -> its pose (mean over the instants it registered at); monocular:
    frame index -> pose. `check(poses)` runs on the registered ones first (the parallax
    rule). Cameras or frames that did not register are dropped and recorded when at least
    `min_registered` remain, else PrepareError naming them."""
    registered = poses(model)
    if check is not None:
        check(registered)
    groups: dict = {}
    for image, pose in registered.items():
        cam, index = chosen[image]
        groups.setdefault(cam if run.kind == "rig" else index, []).append(pose)
    if run.kind == "rig":
        wanted = [s.name for s in run.sources]
        what = "cameras"
    else:
        wanted = [i for _, i in sorted(chosen.values(), key=lambda ci: ci[1])]
        what = "frames"
    missing = [w for w in wanted if w not in groups]
    need = _required(run, len(wanted))
    if len(wanted) - len(missing) < need:
        shown = ", ".join(str(m) for m in missing[:12]) + (" ..." if len(missing) > 12 else "")
        raise PrepareError(f"{what} that failed to register: {shown} ({len(wanted) - len(missing)} "
                           f"of {len(wanted)} registered; --min-registered "
                           f"{len(wanted) - len(missing)} goes on without them)")
    run.record["dropped"] = [{"camera" if run.kind == "rig" else "frame": m,
                              "reason": "not registered by structure from motion"}
                             for m in missing]
    return {key: _mean_pose(items) for key, items in groups.items()}


def _gl_matrix(pose: CameraPose, scale: float, rot: np.ndarray, centre: np.ndarray) -> list:
    """Camera-to-world (OpenGL axes) in the normalised world."""
    c2w = np.eye(4)
    c2w[:3, :3] = rot @ pose.rotation @ np.diag([1.0, -1.0, -1.0])
    c2w[:3, 3] = scale * rot @ (pose.centre - centre)
    return [[float(x) for x in row] for row in c2w]


def _splits(run, cams: dict) -> list[tuple[str, object, int, float]]:
    """(split, camera key, frame index, time) of every frame written. Times are each frame's
    time in the capture normalised to [0, 1]; ``source_time`` in the transforms keeps the
    video's seconds (or the image's index)."""
    rows = []
    if run.kind == "rig":
        names = [s.name for s in run.sources if s.name in cams]
        test = set(run.options.test_cameras) & set(names) or {names[len(names) // 2]}
        n = run.frames
        for name in names:
            split = "test" if name in test else "train"
            rows += [(split, name, i, i / (n - 1)) for i in range(n)]
        run.record["test_cameras"] = sorted(test)
        return rows
    name = run.sources[0].name
    times = run.times[name]
    t0, t1 = times[0], times[-1]
    every = max(int(run.options.test_every), 2)
    for i in sorted(k for k in cams):
        split = "test" if i % every == every // 2 else "train"
        rows.append((split, i, i, (times[i] - t0) / (t1 - t0) if t1 > t0 else 0.0))
    return rows


def _intrinsics(pose: CameraPose) -> dict:
    (fx, fy, cx, cy), _, _ = pinhole(pose.model, pose.params)
    return {"fl_x": fx, "fl_y": fy, "cx": cx, "cy": cy, "w": pose.width, "h": pose.height}


def _write_image(src, dst, pose: CameraPose, maps: dict, key) -> None:
    """Copy a decoded frame, or resample it to the pinhole camera when the model distorts."""
    import cv2

    (fx, fy, cx, cy), k, p = pinhole(pose.model, pose.params)
    if not any(k) and not any(p):
        shutil.copyfile(src, dst)
        return
    if key not in maps:
        mx, my = undistortion_maps(pose.width, pose.height, fx, fy, cx, cy, 0.0, k, p)
        maps[key] = (mx, my)
    img = cv2.imread(str(src), cv2.IMREAD_COLOR)
    out = cv2.remap(img, *maps[key], interpolation=cv2.INTER_LINEAR,
                    borderMode=cv2.BORDER_REPLICATE)
    if not cv2.imwrite(str(dst), out, [cv2.IMWRITE_PNG_COMPRESSION, 1]):
        raise OSError(f"{dst}: cannot write the image")


def write_scene(run, cams: dict, model, out, tick) -> None:
    """The D-NeRF scene of the posed capture into folder `out` (module doc of
    nehad.data.prepare)."""
    keys = list(cams)
    points, colours = sparse_points(model)
    scale, rot, centre = normalisation(np.array([cams[k].centre for k in keys]),
                                       np.array([cams[k].rotation for k in keys]), points)
    shared = len({(c.model, tuple(np.round(c.params, 6))) for c in cams.values()}) == 1
    docs = {"train": [], "test": []}
    maps: dict = {}
    for split, key, i, t in _splits(run, cams):
        cam_name = key if run.kind == "rig" else run.sources[0].name
        file = f"{split}/{cam_name}_{i:06d}.png"
        (out / split).mkdir(exist_ok=True)
        _write_image(run.files[cam_name][i], out / file, cams[key], maps, key if not shared else 0)
        frame = {"file_path": f"./{file}", "time": t, "camera": str(cam_name),
                 "source_time": run.times[cam_name][i],
                 "transform_matrix": _gl_matrix(cams[key], scale, rot, centre)}
        if not shared:
            frame.update(_intrinsics(cams[key]))
        docs[split].append(frame)
        tick()
    top = _intrinsics(cams[keys[0]]) if shared else {}
    if shared:
        top["camera_angle_x"] = float(2.0 * np.arctan(0.5 * top["w"] / top["fl_x"]))
    for split in ("train", "val", "test"):
        frames = docs["test" if split == "val" else split]
        atomic_write_bytes(out / f"transforms_{split}.json", (json.dumps(
            {**top, "frames": frames}, indent=1) + "\n").encode("utf-8"))
    pts = (scale * (points - centre) @ rot.T).astype(np.float32)
    atomic_write_bytes(out / "points3d.ply", points_ply_bytes(pts, colours))
    run.record.update(splits={k: len(v) for k, v in docs.items()}, normalisation={
        "scale": scale, "rotation": rot.tolist(), "centre": centre.tolist()},
        intrinsics=top if shared else "per camera (in the frames)")
