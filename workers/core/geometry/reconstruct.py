"""Map reconstruction on a ground plane: every map camera's pose, aligned to its GPS tag.

Aerial map images over nearly flat ground see one plane, so two overlapping images are
related by a homography and each camera by its pose above the plane. The reconstruction is a
plane-based bundle adjustment (``scipy.optimize.least_squares``, robust soft-L1 loss, sparse
Jacobian):

- unknowns: each reconstructed camera's rotation (a rotation vector) and centre (east,
  north, height above the ground plane), one focal length shared by the map, and the ground's
  altitude in the GPS altitude frame;
- tie points (:mod:`.pairs`): ratio-test matches between GPS-neighbouring map images that survive a RANSAC
  homography; a match (p in image a, q in image b) contributes the symmetric transfer error
  through the ground: p backprojected from a onto ``Z = 0`` and projected into b lands on q,
  and the other way round;
- priors: each camera's centre is its GPS position (sigma ``gps_sigma`` horizontally,
  ``alt_sigma`` vertically above the unknown ground altitude), and the focal length its
  EXIF or assumed value (a loose prior; height and focal trade off on flat ground).

The result places every keypoint of every reconstructed map image on the ground
(:func:`ground_points`): the 3-D points a query frame is registered against
(:mod:`workers.core.geometry.register`). Camera tilt is what this buys over a 2-D image
mosaic: at 75 m above ground a 3 degree tilt moves the image centre 4 m from the nadir point.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.optimize import least_squares
from scipy.sparse import lil_matrix
from scipy.spatial.transform import Rotation

from .camera import Intrinsics, backproject_to_ground, nadir_rotation
from .pairs import PairMatches


@dataclass(frozen=True)
class PlaneReconstruction:
    """Camera poses of the map images over the ground plane ``Z = 0``.

    Attributes
    ----------
    rotations : (N, 3, 3) float64
        World -> camera rotations; NaN rows for images that are not reconstructed.
    centres : (N, 3) float64
        Camera centres (east, north, height above ground); NaN where not reconstructed.
    intrinsics : Intrinsics
    ground_alt : float
        Altitude of the ground plane in the frame of the GPS altitudes (m).
    residual_px : float
        Median reprojection (transfer) error of the tie points after adjustment.
    gps_rms : float
        RMS horizontal distance between reconstructed centres and their GPS positions (m).
    camera_ground_alt : (N,) float64, optional
        Altitude of the ground each camera's height is measured from: its block's, in a map
        adjusted in blocks (:func:`reconstruct_in_blocks`). None: ``ground_alt`` for all.
    """

    rotations: np.ndarray
    centres: np.ndarray
    intrinsics: Intrinsics
    ground_alt: float
    residual_px: float
    gps_rms: float
    camera_ground_alt: np.ndarray | None = None

    @property
    def reconstructed(self) -> np.ndarray:
        """(N,) bool: which map images have a pose."""
        return np.isfinite(self.centres[:, 0])

    def height_offsets(self, altitudes: np.ndarray) -> np.ndarray:
        """(N,) each camera's reconstructed height minus its GPS altitude above the ground it
        was adjusted over; NaN where either is unknown."""
        ground = self.ground_alt if self.camera_ground_alt is None else self.camera_ground_alt
        return self.centres[:, 2] - (np.asarray(altitudes, np.float64) - ground)


def _initial_headings(pairs: list[PairMatches], positions: np.ndarray, K: Intrinsics,
                      n: int) -> tuple[np.ndarray, float]:
    """Per-image heading and a common height from the pair homographies and GPS offsets.

    A nadir camera maps an image vector (du, dv) to the ground vector ``s Rot(theta) (du, -dv)``;
    the displacement of a neighbour's image centre, seen through the homography, against the
    GPS offset gives theta (circular mean, weighted by the offset's length) and s = height / f.
    """
    sin_sum = np.zeros(n)
    cos_sum = np.zeros(n)
    heights = []
    centre = np.array([K.cx, K.cy, 1.0])
    for p in pairs:
        for i, j, H in ((p.a, p.b, np.linalg.inv(p.homography)), (p.b, p.a, p.homography)):
            # centre of image j expressed in the pixels of image i
            c = H @ centre
            if abs(c[2]) < 1e-12:
                continue
            du, dv = c[0] / c[2] - K.cx, c[1] / c[2] - K.cy
            d_gps = positions[j] - positions[i]
            length = float(np.hypot(*d_gps))
            pix = math.hypot(du, dv)
            if length < 1e-6 or pix < 1e-6:
                continue
            theta = math.atan2(d_gps[1], d_gps[0]) - math.atan2(-dv, du)
            sin_sum[i] += length * math.sin(theta)
            cos_sum[i] += length * math.cos(theta)
            heights.append(K.f * length / pix)
    theta = np.arctan2(sin_sum, cos_sum)
    theta[(sin_sum == 0) & (cos_sum == 0)] = np.nan
    height = float(np.median(heights)) if heights else float("nan")
    return theta, height


def _unrobust(r: np.ndarray, scale: float) -> np.ndarray:
    """Residuals whose soft-L1 cost equals their plain squared cost.

    ``least_squares`` applies its robust loss to every residual; the GPS and focal priors
    must stay quadratic, or a camera far from its tag would count as an outlier and drift.
    With ``z = (r / scale)^2``, soft-L1 gives ``2 (sqrt(1 + z') - 1)``, which equals ``z``
    for ``z' = z + z^2 / 4``.
    """
    z = (r / scale) ** 2
    return r * np.sqrt(1.0 + z / 4.0)


def _rotations(rvecs: np.ndarray) -> np.ndarray:
    return Rotation.from_rotvec(rvecs).as_matrix()


def _transfer(Ra, Ca, Rb, Cb, f, c, p):
    """Pixels p of cameras (Ra, Ca) through the ground plane into cameras (Rb, Cb)."""
    rays_c = np.concatenate([(p - c) / f, np.ones((len(p), 1))], axis=1)
    rays = np.einsum("nij,ni->nj", Ra, rays_c)  # R.T @ ray
    t = -Ca[:, 2] / rays[:, 2]
    X = Ca + t[:, None] * rays
    pc = np.einsum("nij,nj->ni", Rb, X - Cb)
    return f * pc[:, :2] / pc[:, 2:3] + c


def _tie_observations(pairs: list[PairMatches], index: np.ndarray
                      ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The tie points of ``pairs`` stacked: each match's two cameras (image indices mapped
    through ``index``) and its pixels in each."""
    a = np.concatenate([np.full(len(p.pa), index[p.a]) for p in pairs])
    b = np.concatenate([np.full(len(p.pa), index[p.b]) for p in pairs])
    return a, b, np.concatenate([p.pa for p in pairs]), np.concatenate([p.pb for p in pairs])


def _transfer_errors(R, C, f, c, a, b, pa, pb) -> np.ndarray:
    """(2n, 2) symmetric transfer errors of n tie points between cameras a and b (rows of
    rotations R and centres C): a's pixels into b, then b's into a."""
    return np.concatenate([_transfer(R[a], C[a], R[b], C[b], f, c, pa) - pb,
                           _transfer(R[b], C[b], R[a], C[a], f, c, pb) - pa])


def reconstruct_plane(pairs: list[PairMatches], positions: np.ndarray, altitudes: np.ndarray,
                      K0: Intrinsics, *, gps_sigma: float = 1.0, alt_sigma: float = 5.0,
                      focal_sigma: float = 0.15, robust_px: float = 2.0,
                      max_nfev: int = 100) -> PlaneReconstruction:
    """Bundle-adjust the map cameras over the ground plane (see the module docstring).

    Parameters
    ----------
    pairs : list of PairMatches
    positions : (N, 2) float ndarray
        GPS east/north (m).
    altitudes : (N,) float ndarray
        GPS altitudes (m); NaN where unknown.
    K0 : Intrinsics
        Initial intrinsics; the focal length is refined with a relative prior
        ``focal_sigma``.
    """
    n = len(positions)
    nan_rec = PlaneReconstruction(np.full((n, 3, 3), np.nan), np.full((n, 3), np.nan), K0,
                                  float("nan"), float("nan"), float("nan"))
    if not pairs:
        return nan_rec
    theta, height = _initial_headings(pairs, positions, K0, n)
    used = np.zeros(n, dtype=bool)
    for p in pairs:
        used[p.a] = used[p.b] = True
    used &= np.isfinite(theta)
    pairs = [p for p in pairs if used[p.a] and used[p.b]]
    if not pairs or not math.isfinite(height):
        return nan_rec
    cams = np.flatnonzero(used)
    slot = np.full(n, -1)
    slot[cams] = np.arange(len(cams))
    m = len(cams)
    alt = np.asarray(altitudes, np.float64)
    has_alt = np.isfinite(alt[cams])
    ground0 = float(np.median(alt[cams][has_alt]) - height) if has_alt.any() else 0.0

    rv0 = Rotation.from_matrix(np.stack([nadir_rotation(t) for t in theta[cams]])).as_rotvec()
    C0 = np.column_stack([positions[cams], np.where(has_alt, alt[cams] - ground0, height)])
    x0 = np.concatenate([rv0.ravel(), C0.ravel(), [math.log(K0.f), ground0]])

    a, b, pa, pb = _tie_observations(pairs, slot)
    c = np.array([K0.cx, K0.cy])
    gps = positions[cams]
    n_obs = len(a)
    i_f, i_g = 6 * m, 6 * m + 1

    def unpack(x):
        rv = x[: 3 * m].reshape(m, 3)
        C = x[3 * m: 6 * m].reshape(m, 3)
        return _rotations(rv), C, math.exp(x[i_f]), x[i_g]

    def residuals(x):
        R, C, f, g = unpack(x)
        ties = _transfer_errors(R, C, f, c, a, b, pa, pb)
        r_xy = (C[:, :2] - gps) / gps_sigma * robust_px
        r_z = np.where(has_alt, (C[:, 2] - (alt[cams] - g)) / alt_sigma * robust_px, 0.0)
        r_f = np.array([(x[i_f] - math.log(K0.f)) / focal_sigma * robust_px])
        priors = _unrobust(np.concatenate([r_xy.ravel(), r_z, r_f]), robust_px)
        out = np.concatenate([ties.ravel(), priors])
        return np.nan_to_num(out, nan=1e3, posinf=1e3, neginf=-1e3)

    n_res = 4 * n_obs + 3 * m + 1
    sparsity = lil_matrix((n_res, 6 * m + 2), dtype=np.int8)
    for block in range(2):
        rows = 2 * block * n_obs + np.arange(2 * n_obs)
        cams_a = np.repeat(a, 2)
        cams_b = np.repeat(b, 2)
        for k in range(3):
            sparsity[rows, 3 * cams_a + k] = 1
            sparsity[rows, 3 * m + 3 * cams_a + k] = 1
            sparsity[rows, 3 * cams_b + k] = 1
            sparsity[rows, 3 * m + 3 * cams_b + k] = 1
        sparsity[rows, i_f] = 1
    base = 4 * n_obs
    for k in range(2):
        sparsity[base + 2 * np.arange(m) + k, 3 * m + 3 * np.arange(m) + k] = 1
    base += 2 * m
    sparsity[base + np.arange(m), 3 * m + 3 * np.arange(m) + 2] = 1
    sparsity[base + np.arange(m), i_g] = 1
    sparsity[n_res - 1, i_f] = 1

    # Variables in comparable units: a pixel of transfer error is about 1/f radians of
    # rotation or height/f metres of position. Unscaled, the sparse solver (LSMR) needs
    # hundreds of inner iterations per step on this badly conditioned problem.
    scale = np.concatenate([np.full(3 * m, 1.0 / K0.f), np.full(3 * m, max(height, 1.0) / K0.f),
                            [1.0 / K0.f, max(height, 1.0) / K0.f]])
    sol = least_squares(residuals, x0, jac_sparsity=sparsity, loss="soft_l1", f_scale=robust_px,
                        max_nfev=max_nfev, method="trf", ftol=1e-4, x_scale=scale)
    R, C, f, g = unpack(sol.x)
    K = Intrinsics(f, K0.cx, K0.cy)
    r = residuals(sol.x)[: 4 * n_obs].reshape(-1, 2)
    rotations = np.full((n, 3, 3), np.nan)
    centres = np.full((n, 3), np.nan)
    rotations[cams] = R
    centres[cams] = C
    gps_rms = float(np.sqrt(np.mean(np.sum((C[:, :2] - gps) ** 2, axis=1))))
    return PlaneReconstruction(rotations, centres, K, float(g),
                               float(np.median(np.linalg.norm(r, axis=1))), gps_rms)


def ground_points(rec: PlaneReconstruction, keypoints: list[np.ndarray]) -> list[np.ndarray]:
    """Every keypoint of every map image on the ground: (K_i, 2) east/north, NaN where the
    image is not reconstructed or the ray misses the ground."""
    out = []
    for i, kp in enumerate(keypoints):
        if not np.isfinite(rec.centres[i, 0]) or len(kp) == 0:
            out.append(np.full((len(kp), 2), np.nan))
            continue
        out.append(backproject_to_ground(rec.rotations[i], rec.centres[i], rec.intrinsics,
                                         np.asarray(kp, np.float64)[:, :2]))
    return out


MAX_BLOCK: int = 250
"""Most cameras in one bundle adjustment. Its cost grows about with the square of the
number of cameras (each sparse solve costs as much as the tie points, and takes more inner
iterations as the chains of cameras grow longer): one adjustment of a 2,000-image survey
ran for over ten minutes, so a large map is adjusted block by block."""


def spatial_blocks(positions: np.ndarray, max_size: int) -> np.ndarray:
    """Cut the map into compact blocks of at most ``max_size`` images.

    Recursive bisection at the median of the longer side of each block's bounding box (a
    k-d tree's cut), so that blocks are contiguous patches of the survey.

    Parameters
    ----------
    positions : (N, 2) float ndarray
    max_size : int

    Returns
    -------
    (N,) int ndarray
        Block index of each image, 0 .. B-1.
    """
    if max_size < 1:
        raise ValueError(f"max_size must be at least 1, got {max_size}")
    positions = np.asarray(positions, np.float64)
    labels = np.zeros(len(positions), dtype=np.int64)
    todo = [np.arange(len(positions))]
    block = 0
    while todo:
        members = todo.pop()
        if len(members) <= max_size:
            labels[members] = block
            block += 1
            continue
        pts = positions[members]
        axis = int(np.argmax(pts.max(axis=0) - pts.min(axis=0)))
        order = members[np.argsort(pts[:, axis], kind="stable")]
        half = len(order) // 2
        todo += [order[half:], order[:half]]
    return labels


@dataclass(frozen=True)
class BlockResult:
    """One block's adjustment (:func:`adjust_block`): the indices of the cameras it placed,
    their world -> camera ``rotations`` and ``centres``, and the block's focal length,
    ground altitude, median residual and GPS RMS."""

    cameras: np.ndarray  # (m,) int64
    rotations: np.ndarray  # (m, 3, 3)
    centres: np.ndarray  # (m, 3)
    focal: float
    ground_alt: float
    residual_px: float
    gps_rms: float


def block_pairs(pairs: list[PairMatches], positions: np.ndarray,
                max_block: int | None = None) -> list[list[PairMatches]]:
    """The pairs inside each compact block of at most ``max_block`` cameras
    (:func:`spatial_blocks`), in the order :func:`reconstruct_in_blocks` adjusts them; pairs
    across two blocks are left out. One block of every pair for a map of at most
    ``max_block`` images (:data:`MAX_BLOCK` by default)."""
    max_block = MAX_BLOCK if max_block is None else max_block
    if len(positions) <= max_block:
        return [list(pairs)]
    labels = spatial_blocks(positions, max_block)
    by_block: dict[int, list[PairMatches]] = {}
    for p in pairs:
        if labels[p.a] == labels[p.b]:
            by_block.setdefault(int(labels[p.a]), []).append(p)
    return list(by_block.values())


def block_key(pairs: list[PairMatches], positions: np.ndarray, altitudes: np.ndarray,
              K0: Intrinsics) -> str:
    """What a block's adjustment depends on, hashed: its tie points, its cameras' GPS
    positions and altitudes and the initial intrinsics. Two equal keys adjust to the same
    cameras (with :func:`adjust_block`'s default options)."""
    import hashlib

    digest = hashlib.sha1()
    cams = np.unique([i for p in pairs for i in (p.a, p.b)]).astype(np.int64)
    for arr in (cams, np.asarray(positions, np.float64)[cams],
                np.asarray(altitudes, np.float64)[cams], np.array([K0.f, K0.cx, K0.cy])):
        digest.update(np.ascontiguousarray(arr).tobytes())
    for p in pairs:
        digest.update(np.array([p.a, p.b], np.int64).tobytes())
        for arr in (p.pa, p.pb, p.homography):
            digest.update(np.ascontiguousarray(arr, np.float64).tobytes())
    return digest.hexdigest()


def adjust_block(pairs: list[PairMatches], positions: np.ndarray, altitudes: np.ndarray,
                 K0: Intrinsics, **options) -> BlockResult | None:
    """:func:`reconstruct_plane` of one block, kept to the cameras it placed; None where it
    placed none."""
    rec = reconstruct_plane(pairs, positions, altitudes, K0, **options)
    done = rec.reconstructed
    if not done.any() or not math.isfinite(rec.residual_px):
        return None
    return BlockResult(np.flatnonzero(done).astype(np.int64), rec.rotations[done],
                       rec.centres[done], rec.intrinsics.f, rec.ground_alt, rec.residual_px,
                       rec.gps_rms)


def reconstruct_in_blocks(pairs: list[PairMatches], positions: np.ndarray,
                          altitudes: np.ndarray, K0: Intrinsics, *,
                          max_block: int | None = None,
                          known: dict[str, BlockResult | None] | None = None,
                          **options) -> PlaneReconstruction:
    """:func:`reconstruct_plane` over compact blocks of at most ``max_block`` cameras.

    Each block is adjusted on its own, with the tie points inside it, over its own ground
    plane. Over flat ground a near-nadir camera's images fix only its height over the focal
    length: the blocks of one survey find focal lengths up to half as large again as each
    other's, with heights to match, and their ground altitudes follow. The map has one
    camera, so its focal length is the median over the blocks (weighted by their cameras)
    and each block is brought to it: heights scaled by the map's focal over the block's,
    which keeps every nadir view's projection of the ground, and the block's ground moved to
    where its GPS altitudes put it under the new heights. The residual is then the median
    over the blocks of their tie points' transfer error with the map's focal length, and the
    GPS RMS is over every camera. A map of at most ``max_block`` images is adjusted whole,
    as :func:`reconstruct_plane` does. ``known`` holds blocks adjusted elsewhere, by
    :func:`block_key`; the others are adjusted here.
    """
    n = len(positions)
    max_block = MAX_BLOCK if max_block is None else max_block
    if n <= max_block:
        return reconstruct_plane(pairs, positions, altitudes, K0, **options)
    altitudes = np.asarray(altitudes, np.float64)
    adjusted: list[tuple[BlockResult, list[PairMatches]]] = []
    for inside in block_pairs(pairs, positions, max_block):
        key = block_key(inside, positions, altitudes, K0) if known else None
        if key is not None and key in known:
            res = known[key]
        else:
            res = adjust_block(inside, positions, altitudes, K0, **options)
        if res is not None:
            adjusted.append((res, inside))
    if not adjusted:
        return reconstruct_plane([], positions, altitudes, K0)
    K = Intrinsics(_weighted_median([(res.focal, len(res.cameras)) for res, _ in adjusted]),
                   K0.cx, K0.cy)
    rotations = np.full((n, 3, 3), np.nan)
    centres = np.full((n, 3), np.nan)
    camera_ground = np.full(n, np.nan)
    ground, residual, sq_gps, weight = [], [], 0.0, 0
    for res, inside in adjusted:
        cams, m = res.cameras, len(res.cameras)
        C = res.centres.copy()
        C[:, 2] *= K.f / res.focal
        known_alt = np.isfinite(altitudes[cams])
        g = (float(np.median(altitudes[cams][known_alt] - C[known_alt, 2])) if known_alt.any()
             else res.ground_alt)
        rotations[cams], centres[cams], camera_ground[cams] = res.rotations, C, g
        ground.append((g, m))
        residual.append(_median_transfer_px(inside, rotations, centres, K))
        sq_gps += res.gps_rms ** 2 * m
        weight += m
    return PlaneReconstruction(rotations, centres, K, _weighted_median(ground),
                               float(np.median(residual)), math.sqrt(sq_gps / weight),
                               camera_ground)


def _median_transfer_px(pairs: list[PairMatches], rotations: np.ndarray, centres: np.ndarray,
                        K: Intrinsics) -> float:
    """Median symmetric transfer error (px) of the tie points of ``pairs`` between placed
    cameras; NaN where no pair joins two of them."""
    placed = [p for p in pairs if np.isfinite(centres[p.a, 0]) and np.isfinite(centres[p.b, 0])]
    if not placed:
        return float("nan")
    a, b, pa, pb = _tie_observations(placed, np.arange(len(centres)))
    err = _transfer_errors(rotations, centres, K.f, np.array([K.cx, K.cy]), a, b, pa, pb)
    return float(np.median(np.linalg.norm(err, axis=1)))


def _weighted_median(values: list[tuple[float, int]]) -> float:
    """Median of ``value`` repeated ``count`` times, over (value, count) pairs."""
    v = np.array([x for x, _ in values], np.float64)
    w = np.array([c for _, c in values], np.float64)
    order = np.argsort(v)
    cum = np.cumsum(w[order])
    return float(v[order][np.searchsorted(cum, 0.5 * cum[-1])])
