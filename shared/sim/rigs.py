"""A realistic simulated camera + projector rig (:func:`make_rig`)."""

from __future__ import annotations

import numpy as np

from shared.formats.rig import Device, Rig
from shared.sim.scenes import rotation_about

__all__ = ["make_rig"]




def make_rig(
    camera_size: tuple[int, int] = (2048, 1536),
    projector_size: tuple[int, int] = (1024, 768),
    seed: int = 0,
    working_distance: float = 1000.0,
    baseline: float = 220.0,
    distortion: bool = True,
    camera_fov_width: float = 490.0,
    projector_throw: float = 1.55,
) -> Rig:
    """A realistic camera + projector rig in mm; ``seed`` perturbs every parameter slightly.

    The camera sits at the origin looking down +Z; its focal length gives ``camera_fov_width`` mm of
    view at ``working_distance`` whatever its resolution (so a 15 MP camera sees the same scene,
    finer). The projector (throw ratio ``projector_throw``) sits ``baseline`` mm to the camera's
    right, toed in so that its axis crosses the camera's at ``working_distance``. Both have small
    lens distortion ``(k1, k2, p1, p2, k3)`` unless ``distortion`` is False.
    """
    rng = np.random.default_rng(seed)
    cw, ch = camera_size
    pw, ph = projector_size
    fc = cw * working_distance / camera_fov_width * (1 + rng.uniform(-0.01, 0.01))
    Kc = np.array([[fc, 0.0, cw / 2 - 0.5 + rng.uniform(-0.015, 0.015) * cw],
                   [0.0, fc * (1 + rng.uniform(-0.001, 0.001)), ch / 2 - 0.5 + rng.uniform(-0.015, 0.015) * ch],
                   [0.0, 0.0, 1.0]])
    fp = pw * projector_throw * (1 + rng.uniform(-0.01, 0.01))
    # Office projectors throw upwards: principal point below the image centre.
    Kp = np.array([[fp, 0.0, pw / 2 - 0.5 + rng.uniform(-0.01, 0.01) * pw],
                   [0.0, fp * (1 + rng.uniform(-0.001, 0.001)), ph * 0.58 + rng.uniform(-0.01, 0.01) * ph],
                   [0.0, 0.0, 1.0]])
    if distortion:
        dc = np.array([-0.07, 0.11, 4e-4, -3e-4, -0.03]) * (1 + rng.uniform(-0.2, 0.2, 5))
        dp = np.array([0.04, -0.05, -2e-4, 3e-4, 0.0]) * (1 + rng.uniform(-0.2, 0.2, 5))
    else:
        dc = np.zeros(5)
        dp = np.zeros(5)
    # Projector centre in the camera frame, and its orientation: toe-in towards the camera axis at
    # the working distance, the principal point's offset taken into account so the projected
    # image's centre lands there.
    C = np.array([baseline, rng.uniform(-8, 8), rng.uniform(-10, 10)])
    target = np.array([0.0, 0.0, working_distance])
    z = target - C
    z /= np.linalg.norm(z)
    x = np.cross([0.0, 1.0, 0.0], z)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    R_cam_from_proj = np.column_stack([x, y, z])
    # Tilt so the projector's image centre (not its principal point) aims at the target.
    tilt = np.degrees(np.arctan2(Kp[1, 2] - (ph / 2 - 0.5), fp))
    R_cam_from_proj = R_cam_from_proj @ rotation_about([1, 0, 0], -tilt)
    R_cam_from_proj = R_cam_from_proj @ rotation_about(rng.normal(size=3), rng.uniform(0.1, 0.4))
    R = R_cam_from_proj.T
    T = -R @ C
    return Rig(camera=Device(cw, ch, Kc, dc), projector=Device(pw, ph, Kp, dp), R=R, T=T)
