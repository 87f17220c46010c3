"""TACTO's side of bench/peers.py: times TACTO's renderer on the workload that bench/peers.py wrote.

Runs in its own environment (``nox -s peers`` makes it: TACTO needs Python 3.8, numpy < 1.24 and pyrender
0.1.45), so it imports neither tnf nor anything newer than TACTO allows. Not meant to be run by hand:

    python bench/peers_tacto.py WORKLOAD.npz RESULT.json

The workload holds each object's mesh (``{name}_vertices`` metres, ``{name}_faces``), its poses in TACTO's sensor
frame (``{name}_poses`` ``[B, 4, 4]``, the object pressed into the gel), the normal forces (newtons), the image
sizes (``sizes`` ``[K, 2]`` width, height) and the number of timed runs. Per frame, TACTO does what its
``Sensor.render`` does once PyBullet has reported the contact: pose the sensor, move the object by the force,
render colour and depth with pyrender, add noise, subtract the undeformed gel's depth. PyBullet itself is not
stepped (that would only add to TACTO's time).

The result: per size, milliseconds per frame (wall clock and this process's CPU time, every run) and the share of
frames in which the object dents the gel (a check that the frames are touches, not empty renders).
"""

import json
import os
import sys
import time

os.environ.setdefault("PYOPENGL_PLATFORM", "egl")

import numpy as np  # noqa: E402
import tacto  # noqa: E402
import trimesh  # noqa: E402
from scipy.spatial.transform import Rotation  # noqa: E402


def time_size(work, width, height):
    """TACTO's milliseconds per frame (every run) at one image size, and the share of frames that dent the gel."""
    names = [str(n) for n in work["names"]]
    forces = work["forces"]
    renderer = tacto.Renderer(width=width, height=height, background=None, config_path=tacto.get_digit_config_path())
    renderer.update_camera_pose([0, 0, 0], [0, 0, 0])
    poses = {}
    for name in names:
        mesh = trimesh.Trimesh(work[name + "_vertices"], work[name + "_faces"], process=False)
        renderer.add_object(mesh, name)
        poses[name] = [
            (p[:3, 3].tolist(), Rotation.from_matrix(p[:3, :3]).as_euler("xyz").tolist()) for p in work[name + "_poses"]
        ]

    def frame(name, k):
        colors, depths = renderer.render({name: poses[name][k]}, {name: float(forces[k])})
        return colors[0], renderer.depth0[0] - depths[0]

    for name in names:  # warm-up: compile shaders, upload every mesh
        frame(name, 0)
    n = sum(len(p) for p in poses.values())
    walls, cpus, touching = [], [], 0
    for run in range(int(work["runs"])):
        np.random.seed(run)
        t0, c0 = time.perf_counter(), time.process_time()
        for name in names:
            for k in range(len(poses[name])):
                _, dent = frame(name, k)
                if run == 0:
                    touching += int((dent > 1e-5).any())
        walls.append((time.perf_counter() - t0) * 1e3 / n)
        cpus.append((time.process_time() - c0) * 1e3 / n)
    renderer.r.delete()
    return {"width": width, "height": height, "wall_ms": walls, "cpu_ms": cpus, "touching": touching / n}


def main():
    work = np.load(sys.argv[1])
    sizes = [time_size(work, int(w), int(h)) for w, h in work["sizes"]]
    with open(sys.argv[2], "w") as f:
        json.dump({"sizes": sizes}, f)


if __name__ == "__main__":
    main()
