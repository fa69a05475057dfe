"""Illuminations of a traversal: sun, sky light, cast shadows and the camera response.

The passes of Weiss et al. 2008 (section V) were recorded on a sunny day, on a cloudy day
and in the evening "when it was starting to get dark"; Flyphone's data set S shows hard
shadows (Erhard et al., section 5.1). Each :class:`Illumination` reproduces one of these:

* ``sunny``: directional sun light, hard cast shadows on the ground and the facades, blue
  sky light in the shadows, high contrast.
* ``cloudy``: no direct light, an overcast sky lighting up-facing surfaces more than
  facades, low contrast.
* ``dusk``: a low, weak orange sun with long soft shadows, blue sky light, dark, a little
  sensor noise.

Shading happens in texture space once per pass: a quad's albedo is multiplied by the light
that reaches it (sun term times its baked shadow mask, plus sky and ground-bounce terms).
The renderer then only samples the shaded textures; :func:`camera_response` applies the
exposure curve and sensor noise to the rendered frame.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, replace

import cv2
import numpy as np

from vloc.clients.world.scene import Plane, Solid
from vloc.clients.world.textures import value_noise


@dataclass(frozen=True, slots=True)
class Illumination:
    """Lighting and camera settings of one traversal.

    Attributes
    ----------
    name : str
    sun_azimuth_deg : float
        Compass bearing of the sun (clockwise from north).
    sun_elevation_deg : float
    sun : (3,) tuple of float
        Direct light, BGR, as a multiple of a white surface's full-scale value.
    sky : (3,) tuple of float
        Light from the whole sky onto an up-facing surface, BGR.
    penumbra_m : float
        Width (Gaussian sigma) of shadow edges on receivers.
    contrast : float
        Slope of the tone curve about mid grey (1 = unchanged).
    gamma : float
        Exponent of the tone curve (greater than 1 darkens the mid tones).
    noise : float
        Standard deviation of the sensor noise, in grey levels.
    horizon, zenith : (3,) tuple of int
        Sky colours, BGR.
    clouds : float
        Cloud cover, 0 to 1.
    cloud_colour : (3,) tuple of int
        BGR.
    exposure_target : float
        Mean grey level the camera's auto exposure aims at.
    max_gain : float
        Largest gain the auto exposure may apply (dark scenes stay dark beyond it).
    time : str
        Local time of day of the first frame, HH:MM:SS.
    day_offset : int
        Days after the first pass's date (the cloudy rounds of Weiss et al. were recorded
        six weeks after the sunny ones).
    """

    name: str
    sun_azimuth_deg: float
    sun_elevation_deg: float
    sun: tuple[float, float, float]
    sky: tuple[float, float, float]
    penumbra_m: float
    contrast: float
    gamma: float
    noise: float
    horizon: tuple[int, int, int]
    zenith: tuple[int, int, int]
    clouds: float
    cloud_colour: tuple[int, int, int]
    exposure_target: float
    max_gain: float
    time: str
    day_offset: int = 0

    @property
    def sun_direction(self) -> np.ndarray:
        """(3,) unit vector from the scene towards the sun (east, north, up)."""
        az, el = math.radians(self.sun_azimuth_deg), math.radians(self.sun_elevation_deg)
        return np.array([math.cos(el) * math.sin(az), math.cos(el) * math.cos(az), math.sin(el)])

    @property
    def has_sun(self) -> bool:
        return max(self.sun) > 0.0 and self.sun_elevation_deg > 0.0

    def to_json(self) -> dict:
        return asdict(self)


ILLUMINATIONS: dict[str, Illumination] = {
    "sunny": Illumination(
        name="sunny", sun_azimuth_deg=205.0, sun_elevation_deg=48.0,
        sun=(0.80, 0.84, 0.86), sky=(0.36, 0.30, 0.26), penumbra_m=0.04,
        contrast=1.05, gamma=1.0, noise=1.0,
        horizon=(235, 214, 190), zenith=(205, 140, 80), clouds=0.25,
        cloud_colour=(250, 250, 250), exposure_target=118.0, max_gain=2.5,
        time="13:37:29", day_offset=0),
    "cloudy": Illumination(
        name="cloudy", sun_azimuth_deg=205.0, sun_elevation_deg=48.0,
        sun=(0.0, 0.0, 0.0), sky=(0.82, 0.82, 0.80), penumbra_m=0.5,
        contrast=0.85, gamma=1.05, noise=1.5,
        horizon=(212, 212, 210), zenith=(190, 188, 186), clouds=1.0,
        cloud_colour=(168, 168, 170), exposure_target=118.0, max_gain=2.0,
        time="11:12:40", day_offset=42),
    "dusk": Illumination(
        name="dusk", sun_azimuth_deg=298.0, sun_elevation_deg=4.0,
        sun=(0.15, 0.33, 0.55), sky=(0.80, 0.64, 0.54), penumbra_m=0.15,
        contrast=1.0, gamma=1.15, noise=2.5,
        horizon=(110, 150, 225), zenith=(95, 55, 35), clouds=0.45,
        cloud_colour=(120, 110, 150), exposure_target=72.0, max_gain=2.0,
        time="21:04:10", day_offset=1),
}
"""The named illuminations a pass can be rendered under."""


def illumination_for_pass(name: str, rng: np.random.Generator) -> Illumination:
    """The named illumination with the small changes a real day brings.

    The sun moves by a few degrees between rounds recorded on different days or hours, so
    each pass jitters the sun direction (and hence its shadows) a little.
    """
    if name not in ILLUMINATIONS:
        raise ValueError(f"unknown illumination {name!r}; choose from {sorted(ILLUMINATIONS)}")
    base = ILLUMINATIONS[name]
    return replace(base,
                   sun_azimuth_deg=round(base.sun_azimuth_deg + rng.uniform(-8.0, 8.0), 3),
                   sun_elevation_deg=round(base.sun_elevation_deg
                                           + rng.uniform(-3.0, 3.0) * (base.sun_elevation_deg > 10),
                                           3))


def shade(plane: Plane, illum: Illumination, shadow: np.ndarray | None) -> np.ndarray:
    """Albedo times the light reaching a quad.

    Parameters
    ----------
    plane : Plane
    illum : Illumination
    shadow : (h, w) float32 ndarray or None
        Share of the sun light blocked at each texel (1 = full shadow).

    Returns
    -------
    (h, w, 3) uint8 ndarray
        Shaded texture, BGR.
    """
    sun = np.asarray(illum.sun, np.float64)
    sky = np.asarray(illum.sky, np.float64)
    if plane.foliage:
        # Leaves scatter light: the sun side of a crown is brighter, the far side still
        # gets some light through the leaves, and the sky lights it from all around.
        direction = plane.u / np.linalg.norm(plane.u)
        s = illum.sun_direction
        side = 0.5 + 0.5 * float(np.dot(direction[:2], s[:2]) / max(np.linalg.norm(s[:2]), 1e-9))
        sun_term = sun * (0.25 + 0.55 * side) if illum.has_sun else 0.0 * sun
        return _scale(plane.albedo, sky * 0.8 + sun_term)
    n = plane.normal
    # Sky light: an up-facing surface sees the whole sky, a facade half of it plus light
    # bounced off the ground.
    ambient = sky * (0.5 + 0.5 * n[2]) + sky * 0.35 * (0.5 - 0.5 * n[2])
    cos_sun = float(np.dot(n, illum.sun_direction)) if illum.has_sun else 0.0
    if cos_sun <= 0.0:
        return _scale(plane.albedo, ambient)
    direct = sun * cos_sun
    if shadow is None:
        return _scale(plane.albedo, ambient + direct)
    # light = ambient + direct * (1 - shadow), per channel, in 1/128 steps: cv2 keeps the
    # multiplication in 8 bits, several times faster than float arrays on large textures.
    light = cv2.merge([cv2.convertScaleAbs(shadow, alpha=-128.0 * d, beta=128.0 * (a + d))
                       for a, d in zip(ambient, direct, strict=True)])
    return cv2.multiply(plane.albedo, light, scale=1.0 / 128.0)


def _scale(albedo: np.ndarray, light: np.ndarray) -> np.ndarray:
    """Albedo times a constant light per channel, saturated to 8 bits."""
    return cv2.multiply(albedo, (float(light[0]), float(light[1]), float(light[2]), 0.0))


def shadow_mask(plane: Plane, solids: list[Solid], illum: Illumination,
                rng: np.random.Generator) -> np.ndarray | None:
    """Cast shadows of ``solids`` on a quad, in its texture space.

    Each solid is projected along the sun direction onto the quad's plane (the parts of it
    behind the plane are clipped away first) and the convex hull of the projection is
    filled. Porous solids (tree crowns) let light through leaf gaps drawn from ``rng``.

    Returns
    -------
    (h, w) float32 ndarray in [0, 1], or None when nothing is in shadow or the quad faces
    away from the sun (then the cosine term already darkens all of it).
    """
    if not illum.has_sun:
        return None
    s = illum.sun_direction
    n = plane.normal
    ns = float(np.dot(n, s))
    if ns <= 1e-3:
        return None
    w, h = plane.size
    solid_layer = np.zeros((h, w), np.uint8)
    porous_layer = np.zeros((h, w), np.uint8)
    uu, vv = plane.u / np.dot(plane.u, plane.u), plane.v / np.dot(plane.v, plane.v)
    drawn = False
    for solid in solids:
        if solid.owner == plane.owner:
            continue
        points = solid.points
        t = (points - plane.origin) @ n / ns
        if t.max() <= 1e-6:
            continue
        if t.min() < -1e-6:
            points = _clip_solid(solid, plane.origin, n, ns)
            if len(points) < 3:
                continue
            t = (points - plane.origin) @ n / ns
        rel = points - t[:, None] * s - plane.origin
        tex = np.stack([rel @ uu, rel @ vv], axis=1)
        if (tex[:, 0].max() < -1 or tex[:, 0].min() > w or tex[:, 1].max() < -1
                or tex[:, 1].min() > h):
            continue
        hull = cv2.convexHull(np.round(tex * 16).astype(np.int32))
        layer = porous_layer if solid.porosity > 0 else solid_layer
        cv2.fillConvexPoly(layer, hull, 255, lineType=cv2.LINE_8, shift=4)
        drawn = True
    if not drawn:
        return None
    mask = solid_layer.astype(np.float32) / 255.0
    texel = float(np.sqrt(np.linalg.norm(plane.u) * np.linalg.norm(plane.v)))
    if porous_layer.any():
        porous = porous_layer.astype(np.float32) / 255.0
        # Sun flecks through the leaves, about 15 cm across.
        gaps = value_noise(rng, (h, w), max(1.5, 0.15 / texel))
        porous *= np.clip(0.85 + 0.9 * gaps, 0.0, 1.0)
        mask = np.maximum(mask, porous)
    sigma = illum.penumbra_m / texel
    if sigma > 0.3:
        mask = cv2.GaussianBlur(mask, (0, 0), sigma)
    return mask


def _clip_solid(solid: Solid, origin: np.ndarray, n: np.ndarray, ns: float) -> np.ndarray:
    """Vertices of the part of a solid on the sun side of a plane (Sutherland-Hodgman)."""
    kept = []
    for face in solid.faces:
        d = (face - origin) @ n / ns
        k = len(face)
        for i in range(k):
            a, b, da, db = face[i], face[(i + 1) % k], d[i], d[(i + 1) % k]
            if da >= 0:
                kept.append(a)
            if (da >= 0) != (db >= 0):
                kept.append(a + (b - a) * (da / (da - db)))
    return np.array(kept) if kept else np.zeros((0, 3))


class AutoExposure:
    """The camera's automatic exposure: a gain that brings the mean grey level towards
    the illumination's target, following changes of the scene within a few frames (a
    shaded street is exposed brighter, and its sky burns out, as with a real camera)."""

    def __init__(self, illum: Illumination) -> None:
        self.target = illum.exposure_target
        self.max_gain = illum.max_gain
        self.gain: float | None = None

    def __call__(self, image: np.ndarray) -> float:
        """Gain for this frame, (H, W, 3) uint8 radiance in."""
        mean = float(np.mean(cv2.mean(image)[:3]))
        want = float(np.clip(self.target / max(mean, 1.0), 0.5, self.max_gain))
        # Half way each frame: exposure control lags behind the scene.
        self.gain = want if self.gain is None else self.gain * math.sqrt(want / self.gain)
        return self.gain


def camera_response(image: np.ndarray, illum: Illumination, rng: np.random.Generator,
                    gain: float = 1.0) -> np.ndarray:
    """Exposure gain, tone curve and sensor noise of the camera for one frame.

    Parameters
    ----------
    image : (H, W, 3) uint8 ndarray
        Rendered radiance, BGR.
    gain : float
        Exposure gain (see :class:`AutoExposure`); the sensor noise grows with it.

    Returns
    -------
    (H, W, 3) uint8 ndarray
    """
    if gain != 1.0:
        image = cv2.multiply(image, (gain, gain, gain, 0.0))
    out = cv2.LUT(image, _tone_curve(illum.contrast, illum.gamma))
    if illum.noise > 0:
        sigma = illum.noise * max(1.0, gain)
        noise = rng.normal(0.0, sigma, image.shape[:2]).astype(np.float32)
        # Mostly luminance noise, as after a camera's demosaicing and denoising.
        out = np.clip(out.astype(np.float32) + noise[..., None], 0, 255).astype(np.uint8)
    return out


def _tone_curve(contrast: float, gamma: float) -> np.ndarray:
    x = np.arange(256, dtype=np.float64) / 255.0
    y = np.power(x, gamma)
    y = 0.5 + contrast * (y - 0.5)
    return np.clip(np.rint(y * 255.0), 0, 255).astype(np.uint8)


SKY_SIZE = (1024, 256)
"""Sky panorama (width, height): compass bearings 0..360 degrees across, elevations from
90 degrees down to :data:`SKY_BOTTOM_DEG`."""

SKY_BOTTOM_DEG = -10.0
"""Lowest elevation the sky panorama covers (below the horizon it shows haze)."""


def sky_panorama(illum: Illumination, rng: np.random.Generator) -> np.ndarray:
    """Sky colours by bearing and elevation: a gradient from horizon to zenith, clouds as
    thresholded fractal noise flattened towards the horizon, and a glow round the sun.

    Returns
    -------
    (256, 1024, 3) uint8 ndarray, BGR
    """
    ws, hs = SKY_SIZE
    elevation = np.linspace(90.0, SKY_BOTTOM_DEG, hs)[:, None]
    bearing = np.linspace(0.0, 360.0, ws, endpoint=False)[None, :]
    t = np.sqrt(np.clip(elevation / 90.0, 0.0, 1.0))[..., None]
    sky = np.asarray(illum.horizon, np.float32) * (1 - t) + np.asarray(illum.zenith, np.float32) * t
    sky = np.broadcast_to(sky, (hs, ws, 3)).astype(np.float32)
    if illum.clouds > 0:
        n = _periodic_noise(rng, (hs, ws), 96) * 0.65 + _periodic_noise(rng, (hs, ws), 24) * 0.35
        # Far clouds are seen edge-on: squeeze their pattern towards the horizon.
        squeeze = np.clip(elevation / 25.0, 0.15, 1.0)
        n = n * squeeze + (1 - squeeze) * n.mean()
        threshold = 0.35 - 0.9 * illum.clouds
        cover = np.clip((n - threshold) * 4.0, 0.0, 1.0)[..., None]
        if illum.clouds >= 1.0:
            cover = np.clip(0.55 + 0.9 * (n[..., None] - n.mean()), 0.0, 1.0)
        sky = sky * (1 - cover) + np.asarray(illum.cloud_colour, np.float32) * cover
    if illum.has_sun:
        s = illum.sun_direction
        el, br = np.radians(elevation), np.radians(bearing)
        ray = np.stack([np.cos(el) * np.sin(br), np.cos(el) * np.cos(br),
                        np.sin(el) * np.ones_like(br)], axis=-1)
        glow = np.clip(ray @ s, 0.0, 1.0) ** 24
        sky = sky + glow[..., None] * (255.0 - sky) * 0.8
    below = elevation[:, 0] < 0
    sky[below] = sky[below] * 0.85
    return np.ascontiguousarray(np.clip(sky, 0, 255).astype(np.uint8))


def _periodic_noise(rng: np.random.Generator, shape: tuple[int, int], cell: int) -> np.ndarray:
    """Value noise that wraps round horizontally (bearing 360 meets bearing 0)."""
    h, w = shape
    gw, gh = max(2, w // cell), max(2, h // cell + 1)
    grid = rng.uniform(-1.0, 1.0, (gh, gw)).astype(np.float32)
    tiled = np.tile(grid, (1, 3))
    big = cv2.resize(tiled, (3 * w, h), interpolation=cv2.INTER_CUBIC)
    return big[:, w:2 * w]
