"""Raw takes from the format readers: the record a reader returns, and the rate and unit checks they share."""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..artifacts import MAX_RATE_HZ, MIN_RATE_HZ
from ..errors import InputError

__all__ = ["RawTake", "UNIT_TO_MM", "check_rate", "unit_factor"]


def check_rate(rate: object, path: str, what: str = "frame rate", fix: str = "export the take again") -> float:
    """``rate`` as a float when it is a number from :data:`MIN_RATE_HZ` to :data:`MAX_RATE_HZ`; else InputError.

    Parameters
    ----------
    rate : object
        The rate as read (any type: a damaged file may hold text, NaN, inf ...).
    path : str
        The file, for the message.
    what : str
        Where the rate comes from (``"POINT:RATE"``, ``"DataRate"`` ...).
    fix : str
        What the user should do.
    """
    ok = isinstance(rate, (int, float, np.integer, np.floating)) and not isinstance(rate, (bool, np.bool_))
    r = float(rate) if ok else float("nan")
    if not (MIN_RATE_HZ <= r <= MAX_RATE_HZ):  # NaN fails too
        shown = f"{r:g} Hz" if ok else repr(rate)[:40]
        raise InputError(
            f"{what} {shown} is not a capture rate (from {MIN_RATE_HZ:g} Hz to {MAX_RATE_HZ:g} Hz) — {fix}", path
        )
    return r


#: Millimetres per unit, keyed by the normalised unit name.
UNIT_TO_MM: dict[str, float] = {"mm": 1.0, "cm": 10.0, "dm": 100.0, "m": 1000.0, "in": 25.4}

_UNIT_ALIASES: dict[str, str] = {
    "mm": "mm", "millimeter": "mm", "millimeters": "mm", "millimetre": "mm", "millimetres": "mm",
    "cm": "cm", "centimeter": "cm", "centimeters": "cm", "centimetre": "cm", "centimetres": "cm",
    "dm": "dm", "decimeter": "dm", "decimeters": "dm", "decimetre": "dm", "decimetres": "dm",
    "m": "m", "meter": "m", "meters": "m", "metre": "m", "metres": "m",
    "in": "in", "inch": "in", "inches": "in",
}


def unit_factor(units: str) -> tuple[str, float | None]:
    """Normalise a length unit name and give its size in millimetres.

    Parameters
    ----------
    units : str
        Unit as written in a file (``"mm"``, ``" MM"``, ``"meters"`` ...).

    Returns
    -------
    name : str
        ``"mm"``, ``"cm"``, ``"dm"``, ``"m"`` or ``"in"``; the stripped input
        when it is not a known length unit.
    factor : float or None
        Millimetres per unit, None when the unit is unknown or empty.
    """
    key = units.strip().strip(".").lower()
    name = _UNIT_ALIASES.get(key)
    if name is None:
        return units.strip(), None
    return name, UNIT_TO_MM[name]


@dataclass
class RawTake:
    """What a format reader hands to :func:`~mocapskel.io.markers.read_markers`.

    points       : (F, M, 3) float64 ndarray, mm, NaN (or another non-finite
                   value) where the marker is not seen; owned by the take.
    labels       : M labels as written in the file (may be empty, repeated,
                   padded or carry a ``Subject:`` prefix).
    rate         : frames per second.
    units        : the file's units, normalised (``"mm"``, ``"m"`` ...).
    descriptions : M point descriptions, or None.
    computed     : labels the file itself declares as computed, with a reason.
    warnings     : what looked wrong in the file and how it was resolved.
    info         : format-specific notes (JSON-able).
    """

    points: np.ndarray
    labels: list[str]
    rate: float
    units: str
    descriptions: list[str] | None = None
    computed: dict[str, str] = field(default_factory=dict)
    warnings: list[str] = field(default_factory=list)
    info: dict = field(default_factory=dict)
