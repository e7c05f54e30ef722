"""Camera models: photons to ADU with noise, ADU back to photons, and the per-pixel noise variance.

Units
-----
Brightness in **photons** (incident on the detector), charge in **electrons** (e-), camera output
in **ADU** (analog-to-digital units). The conversion used everywhere (design.md, section 4) is::

    photons = (ADU - offset) * gain / em_gain / qe

with ``gain`` in e- per ADU. Image arrays are ``(frames, rows, cols)`` or ``(rows, cols)``.

Noise models
------------
``"ideal"``
    Poisson shot noise only: ``e- ~ Poisson(qe * mu)``.
``"emccd"``
    Poisson shot noise, then stochastic electron multiplication modelled as a gamma distribution
    with shape ``n`` (the number of photo-electrons) and scale ``em_gain``; this gives the excess
    noise factor ``F^2 = 2`` of a high-gain EMCCD. Then Gaussian read noise (``read_noise`` e-
    rms at the output).
``"scmos"``
    Poisson shot noise plus per-pixel Gaussian read noise (``variance_map`` in ADU^2, or the
    scalar ``read_noise`` in e- rms), per-pixel gain (``gain_map``) and offset (``offset_map``).
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.special import comb

__all__ = [
    "CAMERA_KINDS",
    "Camera",
    "CameraEstimate",
    "apply_noise",
    "camera_from_options",
    "camera_mismatch",
    "clipping",
    "estimate_camera",
    "gain_mismatch",
    "noise_variance",
    "offset_mismatch",
    "photon_noise",
    "photon_transfer",
    "saturation_level",
    "to_photons",
    "type_saturation",
]

#: Allowed values of :attr:`Camera.kind`.
CAMERA_KINDS: tuple[str, ...] = ("ideal", "emccd", "scmos")

_UINT16_MAX = np.iinfo(np.uint16).max
#: Negative expected photons down to this fraction of the image's peak (or of one photon)
#: count as none (a spline model's undershoot); lower ones are refused.
_NEGATIVE_TOLERANCE = 1e-3


def _as_map(name: str, value: ArrayLike | None) -> NDArray[np.float64] | None:
    if value is None:
        return None
    arr = np.array(value, dtype=np.float64)  # copy: the camera must not change under us
    if arr.ndim != 2 or arr.size == 0:
        raise ValueError(f"{name} must be a 2-D (rows, cols) array, got shape {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{name} must be finite (no NaN or inf)")
    arr.flags.writeable = False
    return arr


_MAP_SUFFIXES = (".tif", ".tiff", ".npy", ".csv")


def _check_map_array(name: str, value: ArrayLike, where: str) -> NDArray[np.float64]:
    """A per-pixel map as a finite float64 (rows, cols) array; leading length-1 axes dropped."""
    try:
        arr = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"the {name} map {where} does not hold numbers ({exc})") from exc
    while arr.ndim > 2 and arr.shape[0] == 1:
        arr = arr[0]
    if arr.ndim != 2 or arr.size == 0:
        raise ValueError(
            f"the {name} map {where} must be one 2-D (rows, cols) image, got shape {arr.shape}"
        )
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"the {name} map {where} holds NaN or infinite values")
    return arr


def _load_map_file(name: str, path: Path) -> NDArray[np.float64]:
    """Read one per-pixel map from a ``.tif``/``.tiff``, ``.npy`` or ``.csv`` file."""
    where = repr(str(path))
    suffix = path.suffix.lower()
    if suffix not in _MAP_SUFFIXES:
        raise ValueError(
            f"the {name} map {where} has an unsupported type {path.suffix or '(none)'!r}; "
            f"use one of {', '.join(_MAP_SUFFIXES)}"
        )
    if not path.exists():
        raise ValueError(f"the {name} map file {where} does not exist")
    if not path.is_file():
        raise ValueError(f"the {name} map {where} is not a file")
    try:
        if suffix == ".npy":
            from .io.npy import load_array

            data = load_array(path)
        elif suffix == ".csv":
            data = np.loadtxt(path, delimiter=",", dtype=np.float64, ndmin=2)
        else:
            from .io.tiff import read_tiff  # the movie reader's checks for damaged files

            data = read_tiff(path)
            data = data[0] if len(data) == 1 else data
    except Exception as exc:  # numpy and tifffile raise many types for a bad file
        raise ValueError(f"the {name} map file {where} could not be read ({exc})") from exc
    if isinstance(data, np.ndarray) and data.dtype.kind not in "biuf":
        raise ValueError(f"the {name} map {where} holds {data.dtype} values, not numbers")
    return _check_map_array(name, data, where)


def _read_map_arguments(
    given: dict[str, Any], kw: dict[str, Any]
) -> tuple[dict[str, NDArray[np.float64]], dict[str, str]]:
    """The maps of :meth:`Camera.from_map_files` (name -> map) and where each came from.

    ``given`` maps "offset", "variance" and "gain" to a file, an array, a number (a scalar
    field, set in ``kw``) or None.
    """
    maps: dict[str, NDArray[np.float64]] = {}
    sources: dict[str, str] = {}
    for name, value in given.items():
        if value is None:
            continue
        if isinstance(value, (str, os.PathLike)):
            maps[name] = _load_map_file(name, Path(value))
            sources[name] = f"{name} {str(value)!r}"
        elif isinstance(value, np.ndarray):
            arr = _check_map_array(name, value, "array")
            maps[name] = arr
            sources[name] = f"{name} array"
        elif name != "variance" and isinstance(value, (int, float, np.number)):
            if isinstance(value, (bool, np.bool_)):
                raise ValueError(f"{name} must be a number or a map file, got {value!r}")
            if name in kw:
                raise ValueError(f"{name} given twice")
            kw[name] = float(value)
        else:
            what = "a map file or an array"
            if name != "variance":
                what = "a map file, an array or a number"
            raise ValueError(f"{name} must be {what}, got {type(value).__name__}")
    return maps, sources


@dataclass(frozen=True, eq=False)
class Camera:
    """Camera parameters that convert between photons and ADU.

    Parameters
    ----------
    kind : {"ideal", "emccd", "scmos"}
        Noise model (see the module docstring).
    offset : float
        Baseline added to every pixel, in ADU (>= 0).
    gain : float
        Conversion gain in e- per ADU (> 0).
    em_gain : float
        Electron-multiplying gain (>= 1); only for ``kind="emccd"``, 1 otherwise.
    qe : float
        Quantum efficiency in (0, 1].
    read_noise : float
        Read noise in e- rms (>= 0); 0 for ``kind="ideal"``. For ``"scmos"`` it applies to every
        pixel unless ``variance_map`` is given.
    offset_map, variance_map, gain_map : ndarray, shape (rows, cols), optional
        sCMOS per-pixel offset (ADU), read-noise variance (ADU^2) and gain (e-/ADU). They replace
        ``offset``, ``read_noise`` and ``gain`` respectively; only for ``kind="scmos"``.

    Raises
    ------
    ValueError
        Naming the offending field and its allowed values.
    """

    kind: str = "ideal"
    offset: float = 100.0
    gain: float = 1.0
    em_gain: float = 1.0
    qe: float = 1.0
    read_noise: float = 0.0
    offset_map: NDArray[np.float64] | None = None
    variance_map: NDArray[np.float64] | None = None
    gain_map: NDArray[np.float64] | None = None

    def __post_init__(self) -> None:
        if self.kind not in CAMERA_KINDS:
            allowed = ", ".join(repr(k) for k in CAMERA_KINDS)
            raise ValueError(f"kind must be one of {allowed}, got {self.kind!r}")
        scalars = {}
        for name in ("offset", "gain", "em_gain", "qe", "read_noise"):
            try:
                v = float(getattr(self, name))
            except (TypeError, ValueError) as exc:
                raise ValueError(f"{name} must be a number, got {getattr(self, name)!r}") from exc
            if not np.isfinite(v):
                raise ValueError(f"{name} must be finite, got {v}")
            scalars[name] = v
            object.__setattr__(self, name, v)
        if scalars["offset"] < 0:
            raise ValueError(f"offset must be >= 0 ADU, got {scalars['offset']}")
        if scalars["gain"] <= 0:
            raise ValueError(f"gain must be > 0 e-/ADU, got {scalars['gain']}")
        if scalars["em_gain"] < 1:
            raise ValueError(f"em_gain must be >= 1, got {scalars['em_gain']}")
        if self.kind != "emccd" and scalars["em_gain"] != 1.0:
            raise ValueError(
                f"em_gain must be 1 unless the camera is an emccd (this one is {self.kind}); "
                f"got {scalars['em_gain']:g}"
            )
        if not 0 < scalars["qe"] <= 1:
            raise ValueError(f"qe must be in (0, 1], got {scalars['qe']}")
        if scalars["read_noise"] < 0:
            raise ValueError(f"read_noise must be >= 0 e- rms, got {scalars['read_noise']}")
        if self.kind == "ideal" and scalars["read_noise"] != 0:
            raise ValueError(
                "read_noise must be 0 for kind='ideal' (Poisson only); "
                "use kind='emccd' or 'scmos' for read noise"
            )
        maps = {}
        for name in ("offset_map", "variance_map", "gain_map"):
            arr = _as_map(name, getattr(self, name))
            if arr is not None and self.kind != "scmos":
                raise ValueError(
                    f"{name} is only allowed with kind='scmos', got kind={self.kind!r}"
                )
            maps[name] = arr
            object.__setattr__(self, name, arr)
        shapes = {m.shape for m in maps.values() if m is not None}
        if len(shapes) > 1:
            raise ValueError(
                "offset_map, variance_map and gain_map must have the same shape, got "
                + ", ".join(f"{k}={v.shape}" for k, v in maps.items() if v is not None)
            )
        if maps["offset_map"] is not None and np.any(maps["offset_map"] < 0):
            raise ValueError("offset_map must be >= 0 ADU everywhere")
        if maps["variance_map"] is not None:
            if np.any(maps["variance_map"] < 0):
                raise ValueError("variance_map must be >= 0 ADU^2 everywhere")
            if scalars["read_noise"] != 0:
                raise ValueError(
                    "give either read_noise (e- rms, all pixels) or variance_map (ADU^2), not both"
                )
        if maps["gain_map"] is not None and np.any(maps["gain_map"] <= 0):
            raise ValueError("gain_map must be > 0 e-/ADU everywhere")

    @classmethod
    def from_map_files(
        cls,
        kind: str = "scmos",
        offset: str | os.PathLike[str] | float | NDArray[np.floating] | None = None,
        variance: str | os.PathLike[str] | NDArray[np.floating] | None = None,
        gain: str | os.PathLike[str] | float | NDArray[np.floating] | None = None,
        **kw: Any,
    ) -> Camera:
        """Camera with sCMOS per-pixel maps read from files.

        Parameters
        ----------
        kind : str
            Noise model; per-pixel maps need ``"scmos"``.
        offset : str or Path or float or ndarray, optional
            Offset map, in ADU, shape (rows, cols): a ``.tif``/``.tiff``, ``.npy`` or ``.csv``
            file (or an array). A number sets the scalar ``offset`` instead.
        variance : str or Path or ndarray, optional
            Read-noise **variance** map, in ADU^2 (not the standard deviation), shape
            (rows, cols): a file as above (or an array).
        gain : str or Path or float or ndarray, optional
            Gain map, in e- per ADU, shape (rows, cols): a file as above (or an array). A
            number sets the scalar ``gain`` instead.
        **kw
            Other :class:`Camera` fields (``qe``, ``em_gain``, ...).

        Returns
        -------
        Camera
            With ``offset_map``, ``variance_map`` and ``gain_map`` set from the files given.

        Raises
        ------
        ValueError
            If no map is given; a file is missing, of an unsupported type or unreadable; a map
            is not a finite 2-D (rows, cols) image; the maps differ in shape; or the camera
            fields are invalid (see :class:`Camera`).

        Notes
        -----
        ``.tif`` maps may hold one image, or a stack of exactly one; ``.npy`` files are read
        with ``allow_pickle=False``; ``.csv`` files hold numbers only (no header), one row of
        the map per line, separated by commas.
        """
        clash = sorted({"offset_map", "variance_map", "gain_map"} & kw.keys())
        if clash:
            raise ValueError(
                f"give the maps as offset=, variance= and gain=, not {', '.join(clash)}"
            )
        maps, sources = _read_map_arguments(
            {"offset": offset, "variance": variance, "gain": gain}, kw
        )
        if not maps:
            raise ValueError("give at least one map file (offset=, variance= or gain=)")
        shapes = {m.shape for m in maps.values()}
        if len(shapes) > 1:
            raise ValueError(
                "the camera maps differ in shape: "
                + ", ".join(f"{sources[k]} is {m.shape[0]} x {m.shape[1]}" for k, m in maps.items())
            )
        return cls(
            kind=kind,
            offset_map=maps.get("offset"),
            variance_map=maps.get("variance"),
            gain_map=maps.get("gain"),
            **kw,
        )

    # Frozen dataclasses compare fields as tuples, which fails for arrays: compare explicitly.
    def __eq__(self, other: object) -> bool:
        if not isinstance(other, Camera):
            return NotImplemented
        for name in ("kind", "offset", "gain", "em_gain", "qe", "read_noise"):
            if getattr(self, name) != getattr(other, name):
                return False
        for name in ("offset_map", "variance_map", "gain_map"):
            a, b = getattr(self, name), getattr(other, name)
            if (a is None) != (b is None) or (a is not None and not np.array_equal(a, b)):
                return False
        return True

    def __hash__(self) -> int:
        return hash((self.kind, self.offset, self.gain, self.em_gain, self.qe, self.read_noise))

    @property
    def photons_per_adu(self) -> float:
        """Photons per ADU above the offset, ``gain / em_gain / qe``: the factor of
        :func:`to_photons` for a camera without a gain map (ValueError otherwise)."""
        if self.gain_map is not None:
            raise ValueError("a camera with a gain map has no single photons-per-ADU factor")
        return self.gain / (self.em_gain * self.qe)

    @property
    def map_shape(self) -> tuple[int, int] | None:
        """Shape ``(rows, cols)`` of the sCMOS maps, or ``None`` when there are none."""
        for m in (self.offset_map, self.variance_map, self.gain_map):
            if m is not None:
                return m.shape  # type: ignore[return-value]
        return None

    def to_dict(self) -> dict:
        """Scalar parameters as a plain dict (maps are summarised by their shape)."""
        return {
            "kind": self.kind,
            "offset": self.offset,
            "gain": self.gain,
            "em_gain": self.em_gain,
            "qe": self.qe,
            "read_noise": self.read_noise,
            "map_shape": self.map_shape,
        }

    # -- per-pixel parameters broadcast to an image ---------------------------------------
    def _pixel_params(
        self, image_shape: tuple[int, ...]
    ) -> tuple[float | NDArray[np.float64], float | NDArray[np.float64]]:
        """Offset (ADU) and gain (e-/ADU) as scalars or (rows, cols) maps checked against
        ``image_shape``."""
        ms = self.map_shape
        if ms is not None and tuple(image_shape[-2:]) != ms:
            raise ValueError(
                f"image of shape {tuple(image_shape)} does not match the camera maps of "
                f"shape {ms} (rows, cols)"
            )
        offset = self.offset_map if self.offset_map is not None else self.offset
        gain = self.gain_map if self.gain_map is not None else self.gain
        return offset, gain

    def _read_variance_e(self, image_shape: tuple[int, ...]) -> float | NDArray[np.float64]:
        """Read-noise variance in e-^2 (scalar or (rows, cols) map)."""
        _, gain = self._pixel_params(image_shape)
        if self.variance_map is not None:
            return self.variance_map * np.asarray(gain) ** 2
        return self.read_noise**2


#: The keys of a camera description in options (the command line's flags, a TOML file's
#: ``[camera]`` table as :func:`sparseloc.options.read_config` gives it) and their
#: :class:`Camera` fields; ``camera`` is the noise model's kind.
CAMERA_OPTION_FIELDS: dict[str, str] = {
    "camera": "kind",
    "offset": "offset",
    "gain": "gain",
    "em_gain": "em_gain",
    "qe": "qe",
    "read_noise": "read_noise",
}
#: The option keys of the sCMOS map files and the :meth:`Camera.from_map_files` argument each
#: fills.
CAMERA_MAP_OPTIONS: dict[str, str] = {
    "offset_map": "offset",
    "variance_map": "variance",
    "gain_map": "gain",
}


#: The refusal of an EMCCD described without its EM gain.
EM_GAIN_NEEDED = (
    "--camera emccd needs --em-gain, the EM register's gain (for example 300; 1 for the "
    "camera's conventional output): without it every count reads as that many times the photons"
)


def camera_from_options(options: dict[str, Any]) -> Camera:
    """The :class:`Camera` that options describe: the one reading of the camera's options by
    every command (``calibrate``, ``localize``, ``simulate``) and the TOML file.

    Parameters
    ----------
    options : dict
        ``camera`` (kind: ideal, emccd or scmos), ``offset`` (ADU), ``gain`` (e-/ADU),
        ``em_gain``, ``qe``, ``read_noise`` (e- rms) and the sCMOS map files ``offset_map``
        (ADU), ``variance_map`` (ADU^2), ``gain_map`` (e-/ADU); missing keys or None take the
        :class:`Camera` defaults.

    Returns
    -------
    Camera

    Raises
    ------
    ValueError
        For invalid values, an EMCCD without its EM gain, or maps without ``camera = "scmos"``
        (one sentence naming the flag).
    """
    kw = {
        field: options[key]
        for key, field in CAMERA_OPTION_FIELDS.items()
        if options.get(key) is not None
    }
    if kw.get("kind") == "emccd" and "em_gain" not in kw:
        raise ValueError(EM_GAIN_NEEDED)
    maps = {arg: options[key] for key, arg in CAMERA_MAP_OPTIONS.items() if options.get(key)}
    if maps and kw.get("kind", "ideal") != "scmos":
        raise ValueError("--offset-map, --variance-map and --gain-map need --camera scmos")
    if maps:
        kw.setdefault("kind", "scmos")
        # A map stands for the scalar of its field (offset, gain), which the options hold too
        # (CAMERA_DEFAULTS fills them): passed both, the field was an argument given twice.
        for field in maps:
            kw.pop(field, None)
        return Camera.from_map_files(**kw, **{k: str(v) for k, v in maps.items()})
    return Camera(**kw)


def check_camera(camera: object) -> None:
    """Raise a ``TypeError`` unless ``camera`` is a :class:`Camera`."""
    if not isinstance(camera, Camera):
        raise TypeError(f"camera must be a Camera, got {type(camera).__name__}")


def _check_expected(expected_photons: ArrayLike) -> NDArray[np.float64]:
    mu = np.asarray(expected_photons, dtype=np.float64)
    if mu.ndim not in (2, 3):
        raise ValueError(
            f"expected_photons must be (rows, cols) or (frames, rows, cols), got shape {mu.shape}"
        )
    if not np.all(np.isfinite(mu)):
        raise ValueError("expected_photons must be finite (no NaN or inf)")
    # A cubic spline model rings slightly below zero beside its empty voxels: such values
    # are no light, not an error. Larger negatives are a caller's mistake.
    tiny = _NEGATIVE_TOLERANCE * max(float(mu.max(initial=0.0)), 1.0)
    if np.any(mu < -tiny):
        raise ValueError("expected_photons must be >= 0")
    return np.maximum(mu, 0.0)


def apply_noise(
    expected_photons: ArrayLike, camera: Camera, rng: np.random.Generator
) -> NDArray[np.uint16]:
    """Draw a noisy camera image from expected photons per pixel.

    Parameters
    ----------
    expected_photons : array_like, shape (frames, rows, cols) or (rows, cols)
        Expected photons per pixel (>= 0), background included.
    camera : Camera
        Camera model.
    rng : numpy.random.Generator
        Source of randomness; the result is a pure function of its state.

    Returns
    -------
    adu : ndarray of uint16, same shape
        Camera counts in ADU, rounded and clipped to [0, 65535].
    """
    check_camera(camera)
    mu = _check_expected(expected_photons)
    offset, gain = camera._pixel_params(mu.shape)
    electrons = rng.poisson(mu * camera.qe).astype(np.float64)
    if camera.kind == "emccd":
        if camera.em_gain != 1.0:
            # Gamma(shape=n, scale=G): the output of a high-gain multiplication register; a
            # shape of 0 gives exactly 0. Mean n*G, variance n*G^2 -> excess noise factor 2.
            electrons = rng.gamma(electrons, camera.em_gain)
        if camera.read_noise > 0:
            electrons = electrons + rng.normal(0.0, camera.read_noise, size=mu.shape)
    elif camera.kind == "scmos":
        var_e = camera._read_variance_e(mu.shape)
        if np.any(np.asarray(var_e) > 0):
            sd = np.sqrt(np.broadcast_to(var_e, mu.shape))
            electrons = electrons + rng.normal(0.0, 1.0, size=mu.shape) * sd
    adu = electrons / gain + offset
    return np.clip(np.rint(adu), 0, _UINT16_MAX).astype(np.uint16)


def to_photons(adu: ArrayLike, camera: Camera) -> NDArray[np.float64]:
    """Convert camera counts to photons: ``(ADU - offset) * gain / em_gain / qe``.

    Parameters
    ----------
    adu : array_like, shape (..., rows, cols)
        Camera counts in ADU (any numeric dtype).
    camera : Camera
        Camera model; sCMOS maps are applied per pixel.

    Returns
    -------
    photons : ndarray of float64, same shape
        Photons per pixel (can be negative where noise pulls the counts below the offset).
    """
    check_camera(camera)
    a = np.asarray(adu, dtype=np.float64)
    if a.ndim < 2 and camera.map_shape is not None:
        raise ValueError(f"adu must be at least 2-D (rows, cols) for sCMOS maps, got {a.shape}")
    offset, gain = camera._pixel_params(a.shape)
    return (a - offset) * (np.asarray(gain) / (camera.em_gain * camera.qe))


def noise_variance(expected_photons: ArrayLike, camera: Camera) -> NDArray[np.float64]:
    """Per-pixel variance, in photons^2, of :func:`to_photons` applied to a noisy image.

    Parameters
    ----------
    expected_photons : array_like, shape (..., rows, cols)
        Expected photons per pixel ``mu`` (>= 0), background included.
    camera : Camera
        Camera model.

    Returns
    -------
    variance : ndarray of float64, same shape
        - ideal: ``mu / qe`` (``mu`` for ``qe = 1``);
        - EMCCD: ``2 mu / qe + (read_noise / (em_gain qe))^2`` (excess noise factor 2 when
          ``em_gain > 1``; ``mu / qe + ...`` at ``em_gain = 1``);
        - sCMOS: ``mu / qe + read variance / qe^2`` with the read variance in e-^2
          (``variance_map * gain_map^2`` or ``read_noise^2``).

        ADU rounding (``gain^2 / 12`` e-^2) is neglected.
    """
    check_camera(camera)
    mu = np.asarray(expected_photons, dtype=np.float64)
    if np.any(mu < 0):
        raise ValueError("expected_photons must be >= 0")
    qe = camera.qe
    if camera.kind == "ideal":
        return mu / qe
    if camera.kind == "emccd":
        enf = 2.0 if camera.em_gain > 1.0 else 1.0
        return enf * mu / qe + (camera.read_noise / (camera.em_gain * qe)) ** 2
    if mu.ndim < 2 and camera.map_shape is not None:
        raise ValueError(
            f"expected_photons must be at least 2-D (rows, cols) for sCMOS maps, got {mu.shape}"
        )
    var_e = camera._read_variance_e(mu.shape)
    return mu / qe + np.asarray(var_e) / qe**2


# -- the camera from the data: photon transfer -------------------------------------------------


def photon_transfer(frames: ArrayLike, block: int = 6) -> tuple[float, float]:
    """The mean-variance (photon transfer) line of camera counts: ``variance = slope * mean
    + intercept``, in ADU and ADU^2, from ``block`` x ``block`` pixel blocks of every frame.

    Each block's noise variance comes from second differences along its rows (smooth
    structure, such as a background gradient or a wide PSF, cancels), divided by 6 (the
    variance of ``a - 2b + c`` for independent pixels); the line is a least-squares fit over
    all blocks, weighted by each block's expected scatter (its variance).

    Parameters
    ----------
    frames : array_like, shape (frames, rows, cols) or (rows, cols)
        Camera counts (ADU); a few frames with a range of brightness give a well-defined line.
    block : int
        Block side (pixels, >= 3).

    Returns
    -------
    slope : float
        ADU per photoelectron (times the excess noise factor of an EMCCD, 2, times its EM
        gain): ``1 / gain`` for an sCMOS or ideal camera with ``gain`` in e-/ADU.
    intercept : float
        ``read variance - slope * offset`` (ADU^2).

    Raises
    ------
    ValueError
        For frames smaller than one block, or blocks that all have the same mean (no line).
    """
    a = np.asarray(frames, dtype=np.float64)
    if a.ndim == 2:
        a = a[None]
    if a.ndim != 3:
        raise ValueError(f"frames must be (frames, rows, cols), got shape {a.shape}")
    block = int(block)
    if block < 3:
        raise ValueError(f"block must be >= 3 pixels, got {block}")
    h, w = (s - s % block for s in a.shape[1:])
    if h == 0 or w == 0:
        raise ValueError(f"frames of {a.shape[1]}x{a.shape[2]} px hold no {block}x{block} block")
    b = a[:, :h, :w].reshape(a.shape[0], h // block, block, w // block, block).swapaxes(2, 3)
    b = b.reshape(-1, block, block)
    d2 = b[:, :, :-2] - 2 * b[:, :, 1:-1] + b[:, :, 2:]
    var = d2.reshape(len(b), -1).var(axis=1) / 6.0
    mean = b.reshape(len(b), -1).mean(axis=1)
    if len(mean) < 2 or np.ptp(mean) <= 0 or not np.all(np.isfinite(mean)):
        raise ValueError(
            "the frames' blocks all have the same brightness: the mean-variance line needs "
            "frames with brighter and darker parts"
        )
    slope, intercept = np.polyfit(mean, var, 1)
    # Each block's variance estimate scatters in proportion to the variance itself, so dark
    # blocks fix the intercept (the read noise) far better than bright ones: refit weighting
    # each block by the inverse of its predicted variance's scatter.
    for _ in range(3):
        pred = slope * mean + intercept
        if not np.all(pred > 0):
            break
        slope, intercept = np.polyfit(mean, var, 1, w=1.0 / pred)
    return float(slope), float(intercept)


#: A series is steady (its frame-to-frame differences are noise alone, as in a bead z-stack's
#: slow steps or flat frames) when fewer than this fraction of its pixels' differences lie more
#: than 4 standard deviations of the line's noise from zero (Gaussian noise: 0.006 %);
#: blinking emitters switch far more.
STEADY_OUTLIERS = 0.01
#: The temporal line needs pixels whose means differ by more than their noise: it is
#: cautioned when the variance of the runs' means is less than this many times the variance
#: their noise alone gives them (a true spread below sqrt(3) noise standard deviations).
MIN_SPREAD = 4.0
#: What the temporal line of an EMCCD says about its own bias (printed with its estimate).
#: (Measurements: docs/benchmarks/camera_estimate.txt.)
EMCCD_CAUTION = (
    "an EMCCD's skewed noise leaves this line uncertain by a few per cent beyond the +- shown "
    "(which is the noise's alone), and its read noise, small beside the amplified shot noise, "
    "is not measured well; prefer the camera's data sheet or its own calibration for an EMCCD"
)
#: A gain whose standard error exceeds this fraction of it is printed with a caution.
GAIN_CAUTION = 0.1
#: Bins of the temporal line over the pixels' mean (equal counts).
_TEMPORAL_BINS = 30
#: What the spatial line says about its own bias (printed with its estimate).
SPATIAL_CAUTION = (
    "the estimate comes from the pixel-to-pixel noise of single frames, and the curvature of "
    "the emitters' images adds to it, so the gain comes out low, by a factor of 2 or more on "
    "simulated single-molecule frames; for a trustworthy value run it on a steady series from "
    "the same camera (a bead z-stack, flat or dark frames) or take the camera's data sheet"
)


def _clipped_variance(d: NDArray[np.float64]) -> float:
    """The variance of zero-mean differences ``d`` without the few beyond 4 standard
    deviations (light that changed between the frames); the clip loses 0.1 % of a Gaussian's
    variance. Started from the median of ``d^2`` (0.4549 of a Gaussian's variance)."""
    var = float(np.median(d**2)) / 0.4549
    for _ in range(3):
        inside = d[d**2 <= 16.0 * var]
        if inside.size == 0 or var <= 0:
            break
        var = float(np.mean(inside**2))
    return var


#: Highest order of the frame-to-frame differences :func:`temporal_transfer` tries.
_MAX_ORDER = 4
#: Two orders' slopes agree when they differ by at most this many standard errors.
_AGREE_SE = 3.0


class TransferLine(NamedTuple):
    """A mean-variance line ``variance = slope * mean + intercept`` (ADU per e-, ADU^2) from
    :func:`temporal_transfer`, with the covariance (2, 2) of (slope, intercept), the order of
    the differences it came from, whether two orders agreed on it, and the fraction of
    differences beyond 4 standard deviations of it. ``spread``: the variance of the
    differenced runs' means over the variance their noise alone gives them; near 1 the
    bins hold noise, not brightness, and the line is not the camera's."""

    slope: float
    intercept: float
    covariance: NDArray[np.float64]
    order: int
    agreed: bool
    outliers: float
    spread: float = np.inf

    @property
    def slope_error(self) -> float:
        """The slope's standard error (ADU per e-)."""
        return float(np.sqrt(max(self.covariance[0, 0], 0.0)))


def _difference_line(a: NDArray[np.float64], order: int) -> TransferLine:
    """The line (not yet ``agreed``) from the ``order``-th differences along the frames
    (variance ``C(2 order, order)`` times a frame's for independent noise), fitted in bins of
    the frames around each run (:func:`_neighbours`). Runs of frames where the light jumps (a
    flat series' change of level: more than :data:`STEADY_OUTLIERS` of their differences
    beyond 4 standard deviations) are left out and the line fitted again, while half of them
    stay."""
    d = np.diff(a, n=order, axis=0)
    m = np.mean([a[i : len(a) - order + i] for i in range(order + 1)], axis=0)
    near = _neighbours(a, order)
    scale = float(comb(2 * order, order))
    line = _binned_line(d.ravel(), m.ravel(), near.ravel(), scale)
    per_run = _beyond(d, m, line, scale).reshape(len(d), -1).mean(axis=1)
    steady = per_run <= STEADY_OUTLIERS
    if 2 * steady.sum() >= len(d) and not steady.all():
        d, m, near = d[steady], m[steady], near[steady]
        line = _binned_line(d.ravel(), m.ravel(), near.ravel(), scale)
    outliers = float(np.mean(_beyond(d, m, line, scale)))
    noise = np.mean(np.maximum(line[0] * m + line[1], 0.0)) / (order + 1)
    spread = float(np.var(m) / noise) if noise > 0 else np.inf
    return TransferLine(line[0], line[1], line[2], order, False, outliers, spread)


def _neighbours(a: NDArray[np.float64], order: int) -> NDArray[np.float64]:
    """For each run of ``order + 1`` frames, each pixel's mean over the frame before the run
    and the frame after it (the one that exists at the series' ends): a measure of its light
    whose noise is independent of the run's."""
    runs = len(a) - order
    start = np.arange(runs)
    before, after = start - 1, start + order + 1
    has_before = (before >= 0)[:, None, None]
    has_after = (after < len(a))[:, None, None]
    total = np.where(has_before, a[np.maximum(before, 0)], 0.0)
    total = total + np.where(has_after, a[np.minimum(after, len(a) - 1)], 0.0)
    return total / (has_before.astype(np.float64) + has_after)


def _beyond(d: NDArray, m: NDArray, line: tuple, scale: float) -> NDArray[np.bool_]:
    """Whether each difference ``d`` lies beyond 4 standard deviations of ``line`` at ``m``."""
    lim = scale * (line[0] * m + line[1])
    with np.errstate(invalid="ignore"):
        return ~(d**2 <= 16.0 * lim)


def _binned_line(
    d: NDArray, m: NDArray, near: NDArray, scale: float
) -> tuple[float, float, NDArray]:
    """Slope, intercept and their covariance (2, 2) of the line through the clipped variance
    of differences ``d`` (divided by ``scale``) against the runs' mean ``m``, in equal-count
    bins of ``near`` (each run's light measured on other frames).

    Bins of ``m`` itself would select on the run's own noise: a bin of runs that read low
    holds pixels brighter than its centre says, and with skewed noise (Poisson, and an
    EMCCD's far more) that noise correlates with the differences' size: the line's slope and
    intercept come out biased (``docs/benchmarks/camera_estimate.txt``). Binned by ``near``
    instead, each bin's mean ``m`` is the mean of its pixels' light."""
    edges = np.quantile(near, np.linspace(0.0, 1.0, _TEMPORAL_BINS + 1))
    idx = np.clip(np.searchsorted(edges, near, side="right") - 1, 0, _TEMPORAL_BINS - 1)
    centre, var, count, members = [], [], [], []
    for k in range(_TEMPORAL_BINS):
        inside_k = np.flatnonzero(idx == k)
        if inside_k.size > 2:
            members.append(inside_k)
            centre.append(float(np.mean(m[inside_k])))
            var.append(_clipped_variance(d[inside_k]) / scale)
            count.append(inside_k.size)
    c, v = np.asarray(centre), np.asarray(var)
    if len(c) < 3 or np.ptp(c) <= 0:
        raise ValueError(
            "the frames all have the same brightness: the mean-variance line needs frames "
            "with brighter and darker parts"
        )
    slope, intercept, _ = _weighted_line(c, v, count)
    # Again with each difference clipped at 4 standard deviations of its own light (``near``)
    # on that line: where most pixels are background, one bin spans the beads' dim wings to
    # their peaks, and a clip at the bin's pooled variance cuts the bright pixels' noise.
    floor = np.min(v)
    v = np.empty(len(members))
    for j, k in enumerate(members):
        dk = d[k]
        limit = 16.0 * scale * np.maximum(slope * near[k] + intercept, floor)
        v[j] = np.mean(dk[dk**2 <= limit] ** 2) / scale
    return _weighted_line(c, v, count)


def _weighted_line(c: NDArray, v: NDArray, count: list[int]) -> tuple[float, float, NDArray]:
    """The line through bin variances ``v`` at means ``c``, each weighted by its scatter
    (about ``v * sqrt(2 / n)`` for ``n`` differences)."""
    sd = np.maximum(v, 1e-12) * np.sqrt(2.0 / np.asarray(count))
    (slope, intercept), cov = np.polyfit(c, v, 1, w=1.0 / sd, cov="unscaled")
    return float(slope), float(intercept), cov


def temporal_transfer(frames: ArrayLike) -> TransferLine:
    """The mean-variance line from frame-to-frame differences of a steady series.

    Where the light does not change between frames, each pixel's differences along the
    frames are noise alone. Light that changes slowly (a bead z-stack's steps, drift,
    bleaching) adds to first differences, less to higher ones: a ``k``-th difference cancels
    change of order below ``k``. The line is fitted to the differences of order 1, 2, ...
    (each in bins of the mean, without differences beyond 4 standard deviations) until two
    consecutive orders give slopes that agree within :data:`_AGREE_SE` standard errors; that
    order's line is returned. If none agree, the light changes faster than the differences
    cancel and the line is marked not agreed.

    Parameters
    ----------
    frames : array_like, shape (frames >= 3, rows, cols)
        Camera counts (ADU).

    Returns
    -------
    TransferLine
        Its ``outliers`` (the fraction of differences beyond 4 standard deviations) above
        :data:`STEADY_OUTLIERS`, or ``agreed`` False, say the series is not steady.
    """
    a = np.asarray(frames, dtype=np.float64)
    if a.ndim != 3 or a.shape[0] < 3:
        raise ValueError("the temporal line needs a series of at least 3 frames")
    top = min(_MAX_ORDER, a.shape[0] - 2)
    lines = [_difference_line(a, 1)]
    for order in range(2, top + 1):
        lines.append(_difference_line(a, order))
        low, high = lines[-2], lines[-1]
        if abs(high.slope - low.slope) <= _AGREE_SE * np.hypot(low.slope_error, high.slope_error):
            return low._replace(agreed=True)
    return lines[-1]


@dataclass(frozen=True)
class CameraEstimate:
    """Camera settings estimated from a movie by :func:`estimate_camera`.

    Attributes
    ----------
    offset : float
        Baseline (ADU): the one given, or estimated (``offset_given`` False).
    gain : float
        Conversion gain (e-/ADU).
    read_noise : float
        Read noise (e- rms); 0 where the line says it is below measurement.
    offset_given : bool
        Whether the offset was given (then the read noise is measured) or estimated (then
        the read noise is taken as the ``read_noise`` given, 0 by default).
    slope, intercept : float
        The photon-transfer line (ADU per e-, ADU^2), see :func:`photon_transfer`.
    method : {"temporal", "spatial"}
        The line's source: a steady series' frame-to-frame differences
        (:func:`temporal_transfer`) or the pixel-to-pixel noise of single frames
        (:func:`photon_transfer`).
    caution : str
        What the user should know about the estimate's trust ("" for none).
    gain_error, offset_error : float
        Standard errors (e-/ADU, ADU) from the line's fit; NaN for the spatial line and
        for a given offset.
    read_noise_bound : float
        With a given offset and the temporal line: the read noise (e- rms) that the line's
        read variance reaches at two standard errors above its estimate; where the estimate
        lies within two standard errors of zero the line does not resolve the read noise,
        only this bound. NaN otherwise.
    """

    offset: float
    gain: float
    read_noise: float
    offset_given: bool
    slope: float
    intercept: float
    method: str = "spatial"
    caution: str = ""
    gain_error: float = float("nan")
    offset_error: float = float("nan")
    read_noise_bound: float = float("nan")

    @property
    def offset_is_bound(self) -> bool:
        """Whether the estimated offset is a lower bound of the camera's to trust: from a
        steady series' line that carries no caution (single frames' emitters, an EMCCD's
        skewed noise or a narrow range of brightness bias the line beyond its standard
        errors, and its intercept far below the data moves with the slope)."""
        return not self.offset_given and self.method == "temporal" and not self.caution

    @property
    def read_noise_resolved(self) -> bool:
        """Whether the line measured the read noise (its read variance lies more than two
        standard errors above zero); where no bound was computed, whether it came out above
        zero."""
        if not np.isfinite(self.read_noise_bound):
            return self.read_noise > 0
        # read_noise^2 = rv g^2 and bound^2 = (rv + 2 se) g^2: rv > 2 se <=> this
        return self.read_noise > 0 and self.read_noise**2 > 0.5 * self.read_noise_bound**2


def estimate_camera(
    frames: ArrayLike,
    *,
    offset: float | None = None,
    read_noise: float | None = None,
    kind: str = "scmos",
    em_gain: float = 1.0,
    block: int = 6,
) -> CameraEstimate:
    """The offset (ADU), gain (e-/ADU) and read noise (e- rms) of the camera that recorded
    ``frames`` (ADU), from their mean-variance line (:func:`photon_transfer`).

    The line's slope gives the gain. Its intercept, ``read variance - slope * offset``, gives
    the read noise where the offset is known, or the offset where the read noise is (0 by
    default: then the estimate is a lower bound, low by ``read variance / slope`` ADU).

    The line comes from the frame-to-frame differences of a steady series (a bead z-stack,
    flat or dark frames: :func:`temporal_transfer`) where the frames are one, else from the
    pixel-to-pixel noise of single frames (:func:`photon_transfer`), which emitters' images
    bias: the estimate then carries a caution.

    Parameters
    ----------
    frames : array_like, shape (frames, rows, cols) or (rows, cols)
        Camera counts (ADU).
    offset : float, optional
        The camera's baseline (ADU), where known.
    read_noise : float, optional
        The read noise (e- rms), where known and ``offset`` is not.
    kind : {"ideal", "emccd", "scmos"}
        Noise model: an EMCCD doubles the shot noise's variance and multiplies it by
        ``em_gain``, which the gain then allows for.
    em_gain : float
        EM gain of an EMCCD (>= 1).
    block : int
        Block side (pixels) of :func:`photon_transfer`.

    Returns
    -------
    CameraEstimate

    Raises
    ------
    ValueError
        For frames without a usable line (flat frames, a slope <= 0) or arguments out of range.
    """
    if kind not in CAMERA_KINDS:
        raise ValueError(f"kind must be one of {', '.join(CAMERA_KINDS)}, got {kind!r}")
    if offset is not None and read_noise is not None:
        raise ValueError("give the offset or the read noise, not both: the other is measured")
    if not em_gain >= 1:
        raise ValueError(f"em_gain must be >= 1, got {em_gain}")
    method, caution, cov = "spatial", SPATIAL_CAUTION, np.full((2, 2), np.nan)
    slope, intercept = photon_transfer(frames, block)
    a = np.asarray(frames)
    if a.ndim == 3 and a.shape[0] >= 3:
        t = temporal_transfer(a)
        if t.agreed and t.outliers < STEADY_OUTLIERS and t.slope > 0:
            method, caution, cov = "temporal", "", t.covariance
            slope, intercept = t.slope, t.intercept
    if not slope > 0:
        raise ValueError(
            f"the frames' variance does not grow with their mean (slope {slope:.3g}); "
            "they are not raw camera counts (ADU)"
        )
    excess = 2.0 * em_gain if kind == "emccd" and em_gain > 1 else 1.0
    gain = excess / slope  # e- per ADU
    gain_error = gain * float(np.sqrt(cov[0, 0])) / slope
    if method == "temporal" and t.spread < MIN_SPREAD:
        caution = (
            "the frames hold one brightness level (the pixels' means differ by no more than "
            "their noise), so the line's slope is not the camera's; use frames with bright "
            "and dark parts (a bead z-stack, or flat frames at several light levels)"
        )
    elif gain_error > GAIN_CAUTION * gain:
        caution = (
            f"the gain is uncertain by {100 * gain_error / gain:.0f} %: the frames span too "
            "narrow a range of brightness; use frames with bright and dark parts (a bead "
            "z-stack, or flat frames at several light levels)"
        )
    elif method == "temporal" and excess > 1:
        caution = EMCCD_CAUTION
    if offset is not None:
        off = float(offset)
        read_var_adu = intercept + slope * off
        noise = float(np.sqrt(max(read_var_adu, 0.0)) * gain)
        # d read variance / d (slope, intercept) = (offset, 1)
        se = float(np.sqrt(max(cov[1, 1] + off**2 * cov[0, 0] + 2 * off * cov[0, 1], 0.0)))
        bound = float(np.sqrt(max(read_var_adu + 2.0 * se, 0.0)) * gain)
        return CameraEstimate(
            off, float(gain), noise, True, slope, intercept, method, caution, gain_error,
            read_noise_bound=bound,
        )  # fmt: skip
    noise = 0.0 if read_noise is None else float(read_noise)
    if noise < 0:
        raise ValueError(f"read_noise must be >= 0 e- rms, got {noise}")
    est_offset = ((noise / gain) ** 2 - intercept) / slope
    # d offset / d intercept = -1 / slope, d offset / d slope = -offset / slope
    var = cov[1, 1] + est_offset**2 * cov[0, 0] + 2 * est_offset * cov[0, 1]
    offset_error = float(np.sqrt(max(var, 0.0))) / slope
    return CameraEstimate(
        float(est_offset),
        float(gain),
        noise,
        False,
        slope,
        intercept,
        method,
        caution,
        gain_error,
        offset_error,
    )


#: Factor between the gain given and the one a steady series' noise measures beyond which
#: :func:`gain_mismatch` speaks; the estimate's own error on simulated bead stacks and flat
#: frames is a few percent, so a factor of 1.5 is a mistake (photons for electrons, a missed
#: EM gain), not the estimate's scatter.
GAIN_MISMATCH: float = 1.5


def _steady_line(frames: ArrayLike, camera: Camera) -> CameraEstimate | None:
    """The estimate of :func:`estimate_camera` (offset not given: its bound) where it comes
    from a steady series without a caution, else None."""
    try:
        est = estimate_camera(frames, kind=camera.kind, em_gain=camera.em_gain)
    except ValueError:
        return None
    if not est.offset_is_bound or not (np.isfinite(est.gain) and est.gain > 0):
        return None
    return est


#: Frames whose largest value this many of their pixel values share were clipped there: counts
#: of light spread over many values, and their maximum is seldom shared by more than a few.
CLIP_TIES = 10


def type_saturation(frames: NDArray) -> float | None:
    """The saturation (ADU) that frames' integer type implies, its largest value; None for
    floating-point frames."""
    return float(np.iinfo(frames.dtype).max) if frames.dtype.kind in "ui" else None


def saturation_level(adu: float, camera: Camera, shape: tuple[int, int]) -> float:
    """The photons at which a frame's pixels (``shape``) reach ``adu`` ADU, the largest over
    them (sCMOS gain and offset maps give each pixel its own): a pixel at its camera's
    saturation is lifted to it when its frame is converted
    (:class:`sparseloc.distributed.CameraFrames`), and no other pixel reaches it."""
    return float(np.max(to_photons(np.full(tuple(shape), float(adu)), camera)))


def clipping(
    raw: NDArray, saturation: float | None = None, ignore: NDArray | None = None
) -> tuple[float, int] | None:
    """Where frames (ADU; a bead stack, a movie's sample) look clipped below ``saturation``
    (default :func:`type_saturation`): their largest value and how many pixel values sit
    there, at least :data:`CLIP_TIES` (a 12-bit camera written to 16-bit files clips at
    4095); else None. Pixels ``ignore`` (H, W; defective ones: a pixel stuck at one value
    is no clipped camera) are left out."""
    if saturation is None:
        saturation = type_saturation(raw)
    if ignore is not None:
        raw = raw[:, ~np.asarray(ignore, dtype=bool)]
    if raw.size == 0:
        return None
    top = float(raw.max())
    if saturation is not None and top >= saturation:
        return None  # the saturation given (or the type's maximum) names these pixels
    ties = int(np.count_nonzero(raw == top))
    return (top, ties) if ties >= CLIP_TIES else None


def photon_noise(camera: Camera | None) -> tuple[float, float]:
    """The camera's noise in photons as ``variance = a * mu + b`` for ``mu`` expected photons:
    ``(a, b)`` from :func:`sparseloc.camera.noise_variance` (an sCMOS map's read variance
    averaged over its pixels); ``(1, 0)``, photon counting, without a camera."""
    if camera is None:
        return 1.0, 0.0
    shape = camera.map_shape or (1, 1)
    zero = noise_variance(np.zeros(shape), camera)
    one = noise_variance(np.ones(shape), camera)
    return float(np.mean(one - zero)), float(np.mean(zero))


def offset_mismatch(frames: ArrayLike, camera: Camera, est: CameraEstimate | None = None) -> str:
    """A warning where a steady series (a bead z-stack) says the camera's offset is higher
    than the one given.

    The mean-variance line places the offset no lower than where the variance would reach
    zero (:func:`estimate_camera` without an offset: a lower bound, low by the read
    variance over the slope). An offset given below that bound by more than three of its
    standard errors, and by more electrons than one and than a pixel's noise at the
    stack's background (a bead stack is not quite steady, and its line's offset is off by
    an ADU or two more than its standard error says; a dark level below that noise changes
    no fit), cannot be the camera's: a forgotten ``--offset`` leaves the dark level in every
    photon count.

    Parameters
    ----------
    frames : array_like, shape (frames, rows, cols)
        Camera counts (ADU) of a steady series.
    camera : Camera
        The camera the user described (scalar offset and gain).
    est : CameraEstimate, optional
        The series' line (:func:`_steady_line`), where already computed.

    Returns
    -------
    str
        "" where the offset given is not below the bound, or the line cannot place it;
        else one sentence naming both.
    """
    est = _steady_line(frames, camera) if est is None else est
    if est is None or not np.isfinite(est.offset_error):
        return ""
    given = float(np.mean(camera.offset))
    gap = est.offset - given
    # the dark level left matters once it stands above a pixel's noise at the background
    background = max(float(np.median(np.asarray(frames))) - est.offset, 0.0) * est.gain
    if gap <= 3.0 * est.offset_error or gap * est.gain <= max(1.0, np.sqrt(background)):
        return ""
    return (
        f"the stack's noise says the camera's offset is at least {est.offset:.1f} ADU (as "
        f"sparseloc camera measures it), not the {given:g} given: the dark level left in the "
        "counts skews the model error and every photon count; give --offset (the median of a "
        "dark frame)"
    )


def camera_mismatch(frames: ArrayLike, camera: Camera) -> str:
    """What a steady series' noise says against the camera described: the warnings of
    :func:`offset_mismatch` and :func:`gain_mismatch` from one line.

    Parameters
    ----------
    frames : array_like, shape (frames, rows, cols)
        Camera counts (ADU) of a steady series (a bead z-stack).
    camera : Camera
        The camera the user described.

    Returns
    -------
    str
        The warnings joined by "; ", or "" for none.
    """
    est = _steady_line(frames, camera)
    if est is None:
        return ""
    warnings = (offset_mismatch(frames, camera, est), gain_mismatch(frames, camera, est))
    return "; ".join(w for w in warnings if w)


def gain_mismatch(frames: ArrayLike, camera: Camera, est: CameraEstimate | None = None) -> str:
    """A warning where a steady series (a bead z-stack) contradicts the camera's gain.

    Parameters
    ----------
    frames : array_like, shape (frames, rows, cols)
        Camera counts (ADU) of a steady series.
    camera : Camera
        The camera the user described (scalar offset and gain).
    est : CameraEstimate, optional
        The series' line (:func:`_steady_line`), where already computed: the gain does not
        depend on the offset.

    Returns
    -------
    str
        "" where the series' mean-variance line agrees with ``camera.gain`` within a factor
        :data:`GAIN_MISMATCH` or three standard errors, or cannot measure it without a caution;
        else one sentence naming both gains.
    """
    est = _steady_line(frames, camera) if est is None else est
    if est is None:
        return ""
    given = float(np.mean(camera.gain))
    ratio = given / est.gain
    if 1.0 / GAIN_MISMATCH <= ratio <= GAIN_MISMATCH or abs(given - est.gain) <= 3 * est.gain_error:
        return ""
    em = f" with an EM gain of {camera.em_gain:g}" if camera.kind == "emccd" else ""
    return (
        f"the stack's noise says the camera's gain is {est.gain:.3g} e-/ADU{em} (as "
        f"sparseloc camera measures it), not the {given:g} given: a wrong --gain (or "
        "--em-gain) skews the model error and every photon count; check them"
    )
