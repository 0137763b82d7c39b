"""The forward-scan sonar: its specification and the beam-bin <-> (θ, R) <-> fan geometry.

Conventions (DESIGN §2): sonar frame +Y along the viewing axis, +X right, +Z up;
``X = R cosφ sinθ, Y = R cosφ cosθ, Z = R sinφ``. A beam-bin image has shape (bins, beams):
row B has range ``R_min + B·δR``, column b has azimuth ``-W_θ + b·δθ`` (or the per-beam angle
table). Radians and metres throughout.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from .errors import InputError, check_integer, is_finite_number, is_number


@dataclass(frozen=True)
class SonarSpec:
    """A multi-beam imaging sonar.

    beams, bins : image columns and rows
    azimuth_fov, elevation_fov : full apertures (rad); the half-angles are W_θ and W_φ
    range_min, range_max : range window (m), the centres of the first and last bin
    beam_angles : optional (beams,) increasing beam-centre azimuths (rad), replacing the
        linear θ_b for lenses with distortion; then azimuth_fov = last - first.
    """

    beams: int = 96
    bins: int = 512
    azimuth_fov: float = math.radians(28.8)
    elevation_fov: float = math.radians(14.0)
    range_min: float = 1.0
    range_max: float = 3.0
    beam_angles: np.ndarray | None = field(default=None, compare=False)

    def __post_init__(self) -> None:
        check_integer("sonar.beams", self.beams, 2)
        check_integer("sonar.bins", self.bins, 2)
        _check_angle("sonar.elevation_fov_deg", self.elevation_fov, math.pi)
        for name, value in (("sonar.range_min_m", self.range_min), ("sonar.range_max_m", self.range_max)):
            if not (is_finite_number(value) and value >= 0):
                raise InputError("must be a finite number >= 0", field=name, value=value)
        if not self.range_max > self.range_min:
            raise InputError(f"must be greater than range_min_m = {self.range_min:g}",
                             field="sonar.range_max_m", value=self.range_max)
        if self.beam_angles is None:
            _check_angle("sonar.azimuth_fov_deg", self.azimuth_fov, math.pi)
            return
        angles = np.asarray(self.beam_angles, dtype=np.float64)
        if angles.shape != (self.beams,):
            raise InputError(f"must list one angle per beam ({self.beams})",
                             field="sonar.beam_angles_deg", value=f"{angles.size} angles")
        if not np.all(np.isfinite(angles)) or np.any(np.diff(angles) <= 0):
            raise InputError("must be finite and strictly increasing", field="sonar.beam_angles_deg",
                             value=np.round(np.degrees(angles[:4]), 3).tolist())
        if np.max(np.abs(angles)) >= math.pi / 2:
            raise InputError("must lie inside (-90, 90) degrees", field="sonar.beam_angles_deg",
                             value=float(np.degrees(np.max(np.abs(angles)))))
        fov = float(angles[-1] - angles[0])
        if abs(fov - self.azimuth_fov) > 0.5 * fov / (self.beams - 1):
            raise InputError(f"disagrees with beam_angles_deg, which span {math.degrees(fov):.4g} deg",
                             field="sonar.azimuth_fov_deg", value=round(math.degrees(self.azimuth_fov), 6))
        angles.setflags(write=False)
        object.__setattr__(self, "beam_angles", angles)

    @classmethod
    def from_degrees(cls, *, beams: int = 96, bins: int = 512, azimuth_fov_deg: float | None = 28.8,
                     elevation_fov_deg: float = 14.0, range_min_m: float = 1.0, range_max_m: float = 3.0,
                     beam_angles_deg=None) -> "SonarSpec":
        """A sonar from the degree-valued fields of a manifest's ``[sonar]`` table."""
        angles = None if beam_angles_deg is None else np.radians(np.asarray(beam_angles_deg, dtype=float))
        if azimuth_fov_deg is None:
            if angles is None:
                raise InputError("is required without beam_angles_deg", field="sonar.azimuth_fov_deg")
            azimuth_fov = float(angles[-1] - angles[0]) if angles.size > 1 else 0.0
        else:
            azimuth_fov = _radians("sonar.azimuth_fov_deg", azimuth_fov_deg)
        return cls(beams=beams, bins=bins, azimuth_fov=azimuth_fov,
                   elevation_fov=_radians("sonar.elevation_fov_deg", elevation_fov_deg),
                   range_min=range_min_m, range_max=range_max_m, beam_angles=angles)

    def to_degrees(self) -> dict:
        """The manifest's ``[sonar]`` table (degrees)."""
        table = {"beams": self.beams, "bins": self.bins,
                 "azimuth_fov_deg": math.degrees(self.azimuth_fov),
                 "elevation_fov_deg": math.degrees(self.elevation_fov),
                 "range_min_m": self.range_min, "range_max_m": self.range_max}
        if self.beam_angles is not None:
            table["beam_angles_deg"] = np.degrees(self.beam_angles).tolist()
        return table

    @property
    def half_azimuth(self) -> float:
        """W_θ (rad)."""
        return 0.5 * self.azimuth_fov

    @property
    def half_elevation(self) -> float:
        """W_φ (rad)."""
        return 0.5 * self.elevation_fov

    @property
    def range_step(self) -> float:
        """δR (m)."""
        return (self.range_max - self.range_min) / (self.bins - 1)

    @property
    def beam_centres(self) -> np.ndarray:
        """(beams,) azimuth of each column (rad)."""
        if self.beam_angles is not None:
            return self.beam_angles
        return -self.half_azimuth + np.arange(self.beams) * (self.azimuth_fov / (self.beams - 1))

    @property
    def beam_widths(self) -> np.ndarray:
        """(beams,) float32 azimuth width Δθ_b of every beam (rad): the spacing of the centres
        (central differences inside, one-sided at the outer beams)."""
        return np.gradient(np.asarray(self.beam_centres, np.float64)).astype(np.float32)

    @property
    def bin_ranges(self) -> np.ndarray:
        """(bins,) range of each row (m)."""
        return self.range_min + np.arange(self.bins) * self.range_step

    # --- conversions -------------------------------------------------------------------
    def beam_coordinate(self, theta) -> np.ndarray:
        """Fractional column index of azimuth ``theta`` (rad); integers at beam centres.

        Linear beyond the outer beams (with the outer spacing), so out-of-fan angles map
        outside [-0.5, beams - 0.5)."""
        theta = np.asarray(theta, dtype=np.float64)
        if self.beam_angles is None:
            return (theta + self.half_azimuth) * ((self.beams - 1) / self.azimuth_fov)
        c = self.beam_angles
        inside = np.interp(theta, c, np.arange(self.beams))
        below = (theta - c[0]) / (c[1] - c[0])
        above = self.beams - 1 + (theta - c[-1]) / (c[-1] - c[-2])
        return np.where(theta < c[0], below, np.where(theta > c[-1], above, inside))

    def beam_angle(self, beam) -> np.ndarray:
        """Azimuth (rad) of fractional column index ``beam`` (inverse of beam_coordinate)."""
        beam = np.asarray(beam, dtype=np.float64)
        if self.beam_angles is None:
            return -self.half_azimuth + beam * (self.azimuth_fov / (self.beams - 1))
        c = self.beam_angles
        inside = np.interp(beam, np.arange(self.beams), c)
        below = c[0] + beam * (c[1] - c[0])
        above = c[-1] + (beam - (self.beams - 1)) * (c[-1] - c[-2])
        return np.where(beam < 0, below, np.where(beam > self.beams - 1, above, inside))

    def bin_coordinate(self, rng) -> np.ndarray:
        """Fractional row index of range ``rng`` (m)."""
        return (np.asarray(rng, dtype=np.float64) - self.range_min) / self.range_step

    def bin_range(self, bin_index) -> np.ndarray:
        """Range (m) of fractional row index ``bin_index``."""
        return self.range_min + np.asarray(bin_index, dtype=np.float64) * self.range_step

    def beam_bin(self, theta, rng):
        """Nearest (beam, bin) integer indices of returns at (θ, R) and whether they land in
        the image. Returns ``(beam, bin, inside)``, arrays of the broadcast shape."""
        b = np.floor(self.beam_coordinate(theta) + 0.5)
        B = np.floor(self.bin_coordinate(rng) + 0.5)
        inside = (b >= 0) & (b < self.beams) & (B >= 0) & (B < self.bins)
        return b.astype(np.int64), B.astype(np.int64), inside

    def in_elevation(self, phi) -> np.ndarray:
        """Whether elevation ``phi`` (rad) lies inside [-W_φ, W_φ]."""
        return np.abs(np.asarray(phi)) <= self.half_elevation

    def in_window(self, rng, theta, phi) -> np.ndarray:
        """Whether returns at (R, θ, φ) (as :func:`to_polar` gives them) land in the image
        (:meth:`beam_bin`) and in the elevation aperture."""
        return self.beam_bin(theta, rng)[2] & self.in_elevation(phi)

    # --- images ----------------------------------------------------------------------------
    def check_image(self, image, *, file=None, field: str = "image") -> np.ndarray:
        """``image`` as a (bins, beams) float32 array of finite values >= 0 (linear intensity),
        or InputError."""
        array = np.asarray(image)
        if array.shape != (self.bins, self.beams):
            raise InputError(f"shape must be (bins, beams) = ({self.bins}, {self.beams})",
                             file=file, field=field, value=tuple(array.shape))
        if array.dtype != np.float32:
            raise InputError("dtype must be float32", file=file, field=field, value=str(array.dtype))
        if not np.all(np.isfinite(array)):
            raise InputError("holds non-finite values", file=file, field=field,
                             value=f"{int(np.size(array) - np.isfinite(array).sum())} NaN/inf")
        if array.size and array.min() < 0:
            raise InputError("must be linear intensity >= 0", file=file, field=field, value=float(array.min()))
        return array


def to_polar(points) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(R, θ, φ) of (..., 3) sonar-frame points (paper eq. 1)."""
    p = np.asarray(points, dtype=np.float64)
    x, y, z = p[..., 0], p[..., 1], p[..., 2]
    return np.sqrt(x * x + y * y + z * z), np.arctan2(x, y), np.arctan2(z, np.hypot(x, y))


def from_polar(rng, theta, phi) -> np.ndarray:
    """(..., 3) sonar-frame points at range ``rng``, azimuth ``theta``, elevation ``phi`` (eq. 1)."""
    rng, theta, phi = np.broadcast_arrays(*(np.asarray(a, dtype=np.float64) for a in (rng, theta, phi)))
    c = np.cos(phi)
    return np.stack([rng * c * np.sin(theta), rng * c * np.cos(theta), rng * np.sin(phi)], axis=-1)


def fan_xy(theta, rng) -> tuple[np.ndarray, np.ndarray]:
    """Fan-image coordinates (x, y) = R (sin θ, cos θ) (paper eq. 3)."""
    theta = np.asarray(theta, dtype=np.float64)
    rng = np.asarray(rng, dtype=np.float64)
    return rng * np.sin(theta), rng * np.cos(theta)


def scan_convert(image, sonar: SonarSpec, *, pixel_m: float | None = None, fill: float = np.nan):
    """Resample a (bins, beams) beam-bin image onto a Cartesian fan image for figures.

    Returns ``(fan, extent)``: ``fan`` is (rows, cols) float32 with row 0 at the far range
    (y = R_max, top of a figure) and ``fill`` outside the fan; ``extent`` = (x0, x1, y0, y1)
    in metres for ``matplotlib.imshow(fan, extent=extent)``. Bilinear in (beam, bin).
    """
    from scipy.ndimage import map_coordinates

    array = np.asarray(image, dtype=np.float32)
    if array.shape != (sonar.bins, sonar.beams):
        raise InputError(f"shape must be (bins, beams) = ({sonar.bins}, {sonar.beams})",
                         field="image", value=tuple(array.shape))
    if pixel_m is None:
        pixel_m = sonar.range_step
    if not (pixel_m > 0 and math.isfinite(pixel_m)):
        raise InputError("must be > 0", field="pixel_m", value=pixel_m)
    centres = sonar.beam_centres
    half_beam = 0.5 * (centres[-1] - centres[0]) / (sonar.beams - 1)
    left, right = centres[0] - half_beam, centres[-1] + half_beam
    r1 = sonar.range_max
    r0 = sonar.range_min
    xs = [r1 * math.sin(left), r1 * math.sin(right), r0 * math.sin(left), r0 * math.sin(right), 0.0]
    ys = [r0 * math.cos(left), r0 * math.cos(right), r0, r1]
    x0, x1 = min(xs), max(xs)
    y0, y1 = min(ys), r1
    cols = max(2, int(math.ceil((x1 - x0) / pixel_m)) + 1)
    rows = max(2, int(math.ceil((y1 - y0) / pixel_m)) + 1)
    x = x0 + np.arange(cols) * pixel_m
    y = y1 - np.arange(rows) * pixel_m
    gx, gy = np.meshgrid(x, y)
    rng = np.hypot(gx, gy)
    theta = np.arctan2(gx, gy)
    b = sonar.beam_coordinate(theta)
    B = sonar.bin_coordinate(rng)
    inside = (b >= -0.5) & (b <= sonar.beams - 0.5) & (B >= -0.5) & (B <= sonar.bins - 0.5)
    values = map_coordinates(array, [np.clip(B, 0, sonar.bins - 1), np.clip(b, 0, sonar.beams - 1)],
                             order=1, mode="nearest")
    fan = np.where(inside, values, fill).astype(np.float32)
    return fan, (x0 - 0.5 * pixel_m, x[-1] + 0.5 * pixel_m, y[-1] - 0.5 * pixel_m, y1 + 0.5 * pixel_m)


def _check_angle(name: str, value, maximum: float) -> None:
    if not (is_finite_number(value) and 0 < value < maximum):
        raise InputError(f"must be in (0, {math.degrees(maximum):g}) degrees", field=name,
                         value=math.degrees(value) if is_number(value) else value)


def _radians(name: str, degrees) -> float:
    if not is_number(degrees):
        raise InputError("must be a number (degrees)", field=name, value=degrees)
    return math.radians(degrees)
