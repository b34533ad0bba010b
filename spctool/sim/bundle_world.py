"""Synthetic landmark-refinement problems with their truth (map-refinement.md §3).

A spherical body of radius ``radius_km`` carries ``n_landmarks`` landmarks spread uniformly over its
surface; ``n_pictures`` frame cameras orbit at ``distance_km`` from its centre, each looking at the
surface point below it (plus a random pointing offset and roll).  A landmark is measured in a picture
when it projects inside the photo and faces the camera (emission below ``max_emission_deg``).  The
measured pixels are the truth's projection plus Gaussian noise ``sigma_px``; the a-priori poses and
landmark positions are the truth plus Gaussian errors of the stated sigmas, and the priors carry those
same sigmas (``prior_scale`` multiplies them: an understated prior has ``prior_scale < 1``).

Used by the bundle-adjustment tests (exact measurements, 1/√N, NEES, outliers, calibration) and the
``geometry`` benchmark's 2,000-picture problem.  Vectorised: the truth projection of every
(picture, landmark) pair is one pass per camera group.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from spctool.geometry.camera import Camera
from spctool.geometry.frames import look_rotation, rot_from_rotvec
from spctool.stages.bundle import BundleProblem

__all__ = ["BundleWorld", "bundle_world", "demo_camera"]


def demo_camera(npx: int = 1024, fov_deg: float = 20.0, mmfl: float = 100.0) -> Camera:
    """A distortion-free frame camera with a square field of ``fov_deg`` (K = px/mm on the diagonal)."""
    half = np.radians(fov_deg) / 2.0
    k = (npx / 2.0) / (mmfl * np.tan(half))
    return Camera(
        mmfl=mmfl,
        ctr=np.array([npx / 2.0 + 0.5, npx / 2.0 + 0.5]),
        kmatrix=np.array([[k, 0.0, 0.0], [0.0, k, 0.0]]),
        rotation=np.eye(3),
        scobj=np.array([0.0, 0.0, -10.0]),
        npx=npx,
        nln=npx,
    )


@dataclass
class BundleWorld:
    """A problem (a-priori values, noisy measurements) and its truth."""

    problem: BundleProblem
    true_positions: np.ndarray  # (P, 3) spacecraft positions
    true_rotations: np.ndarray  # (P, 3, 3)
    true_landmarks: np.ndarray  # (L, 3)
    true_pixels: np.ndarray  # (K, 2) noise-free measurements


def _unit(rng, n) -> np.ndarray:
    v = rng.standard_normal((n, 3))
    return v / np.linalg.norm(v, axis=1, keepdims=True)


def bundle_world(
    n_pictures: int = 20,
    n_landmarks: int = 200,
    *,
    seed: int = 0,
    radius_km: float = 0.3,
    distance_km: float = 0.9,
    camera: Camera | None = None,
    sigma_px: float = 0.1,
    sigma_position_km: float = 0.002,
    sigma_attitude_rad: float = 2e-4,
    sigma_landmark_km: float = 0.001,
    prior_scale: float = 1.0,
    max_emission_deg: float = 60.0,
    pointing_spread: float = 0.5,
    cap_deg: float = 40.0,
) -> BundleWorld:
    """A random world (module docstring).  ``cap_deg`` < 180 keeps cameras and landmarks within a cap
    of that half-angle around +z (a local mapping campaign); ``pointing_spread`` is the random pointing
    offset as a fraction of the half field of view."""
    rng = np.random.default_rng(seed)
    cam0 = camera or demo_camera()

    # landmarks and camera directions, uniform over the cap
    def cap_dirs(n):
        cosmin = np.cos(np.radians(cap_deg))
        z = rng.uniform(cosmin, 1.0, n)
        phi = rng.uniform(0, 2 * np.pi, n)
        s = np.sqrt(1 - z * z)
        return np.stack([s * np.cos(phi), s * np.sin(phi), z], axis=1)

    lm_true = radius_km * cap_dirs(n_landmarks)
    dirs = cap_dirs(n_pictures)
    pos_true = distance_km * dirs
    half = np.arctan((cam0.npx / 2.0) / (cam0.mmfl * cam0.kmatrix[0, 0]))
    rots = []
    for j in range(n_pictures):  # one look rotation per picture (P small 3×3 builds)
        target = radius_km * dirs[j] + rng.standard_normal(3) * pointing_spread * half * (
            distance_km - radius_km
        )
        rots.append(look_rotation(pos_true[j], target, roll_deg=float(rng.uniform(0, 360))))
    rot_true = np.array(rots)
    # which landmark is seen where: every pair, vectorised over landmarks per picture
    obs_p, obs_l, pix = [], [], []
    normals = lm_true / radius_km
    cosmax = np.cos(np.radians(max_emission_deg))
    for j in range(n_pictures):
        cam = cam0.with_pose(position=pos_true[j], rotation=rot_true[j])
        smp, lin, front = cam.project_with_mask(lm_true)
        view = pos_true[j] - lm_true
        view /= np.linalg.norm(view, axis=1, keepdims=True)
        ok = front & cam.in_image(smp, lin) & (np.sum(view * normals, axis=1) > cosmax)
        idx = np.flatnonzero(ok)
        obs_p.append(np.full(idx.size, j))
        obs_l.append(idx)
        pix.append(np.stack([smp[idx], lin[idx]], axis=1))
    obs_p = np.concatenate(obs_p)
    obs_l = np.concatenate(obs_l)
    true_pix = np.concatenate(pix).reshape(-1, 2)
    meas = true_pix + rng.standard_normal(true_pix.shape) * sigma_px
    # a-priori values
    pos0 = pos_true + rng.standard_normal(pos_true.shape) * sigma_position_km
    theta = rng.standard_normal((n_pictures, 3)) * sigma_attitude_rad
    rot0 = rot_from_rotvec(theta) @ rot_true  # T⁰ = Rot(θ)·T: the truth is Rot(−θ)·T⁰
    lm0 = lm_true + rng.standard_normal(lm_true.shape) * sigma_landmark_km
    cams = [cam0.with_pose(position=pos0[j], rotation=rot0[j]) for j in range(n_pictures)]
    w = np.broadcast_to(np.eye(2) / sigma_px**2, (meas.shape[0], 2, 2)).copy()
    prob = BundleProblem(
        cameras=cams,
        picture_names=[f"P{j:05d}" for j in range(n_pictures)],
        sigma_position=np.full((n_pictures, 3), sigma_position_km * prior_scale),
        sigma_attitude=np.full((n_pictures, 3), sigma_attitude_rad * prior_scale),
        landmark_names=[f"L{i:05d}" for i in range(n_landmarks)],
        landmark_positions=lm0,
        landmark_sigmas=np.full((n_landmarks, 3), sigma_landmark_km * prior_scale),
        obs_picture=obs_p,
        obs_landmark=obs_l,
        obs_pixel=meas,
        obs_weight=w,
    )
    return BundleWorld(prob, pos_true, rot_true, lm_true, true_pix)
