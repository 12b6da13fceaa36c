"""Camera response curves of the virtual rig: how a linear exposure becomes an encoded pixel value.

A camera's image pipeline maps the sensor's linear signal (a fraction of full scale, 0..1) to
the stored value through a response curve before quantisation. The virtual rig applies
``"srgb"`` by default (IEC 61966-2-1's transfer function: linear below 0.0031308, then
1.055 x^(1/2.4) - 0.055), as a consumer or machine-vision camera set to sRGB output does;
``"linear"`` stores the signal as it is; ``"gamma:G"`` (e.g. ``"gamma:2.2"``) a pure power
x^(1/G). The name is recorded in each capture's ``capture.json`` (``extra.simulated.imaging``)
and ``truth.npz`` (``response``).

    y = apply_response(x, "srgb")       # linear fraction -> encoded fraction, float64
    x = linearise(y, "srgb")            # its inverse
    codes = response_codes("srgb", 8)   # stored value of every fine linear step, for the sensor kernel
"""

from __future__ import annotations

import numpy as np

from shared.core.errors import InputError

__all__ = ["RESPONSES", "apply_response", "check_response", "linearise", "response_codes"]

#: The named responses (``"gamma:G"`` takes any G in 1..4 as well).
RESPONSES = ("linear", "srgb")


def check_response(response: str) -> float | None:
    """Validate a response name; returns the exponent G of ``"gamma:G"``, else None."""
    if response in RESPONSES:
        return None
    if isinstance(response, str) and response.startswith("gamma:"):
        try:
            g = float(response[6:])
        except ValueError:
            g = float("nan")
        if 1.0 <= g <= 4.0:
            return g
    raise InputError("response", f"must be one of {', '.join(RESPONSES)} or gamma:G with G in 1..4, got {response!r}")


def _curve(v: np.ndarray, response: str, inverse: bool) -> np.ndarray:
    """The response (``inverse``: its inverse) applied to values ``v`` clipped to 0..1, float64."""
    g = check_response(response)
    v = np.clip(np.asarray(v, np.float64), 0.0, 1.0)
    if response == "linear":
        return v
    if g is not None:
        return v**g if inverse else v ** (1.0 / g)
    if inverse:
        return np.where(v <= 0.04045, v / 12.92, ((v + 0.055) / 1.055) ** 2.4)
    return np.where(v <= 0.0031308, 12.92 * v, 1.055 * v ** (1 / 2.4) - 0.055)


def apply_response(x: np.ndarray, response: str) -> np.ndarray:
    """Encoded values (float64, 0..1) of linear signals ``x`` (any shape; clipped to 0..1)."""
    return _curve(x, response, inverse=False)


def linearise(y: np.ndarray, response: str) -> np.ndarray:
    """Linear signals (float64, 0..1) of encoded values ``y`` (fractions of full scale, 0..1)."""
    return _curve(y, response, inverse=True)


def response_codes(response: str, bits: int) -> np.ndarray:
    """The stored value (uint16) of each of K even steps of the linear signal over 0..1; empty for linear.

    The sensor rounds its linear signal to the nearest step and reads the code: K is 2^16 for 8-bit
    images and 2^20 for 16-bit ones, fine enough that the steepest part of the curve (sRGB's
    12.92 near black) moves a value by at most 0.05 of an 8-bit step or 0.8 of a 16-bit one.
    """
    check_response(response)
    if response == "linear":
        return np.zeros(0, np.uint16)
    k = 1 << (16 if bits <= 8 else 20)
    maxval = (1 << bits) - 1
    y = apply_response(np.linspace(0.0, 1.0, k), response)
    return np.floor(y * maxval + 0.5).astype(np.uint16)
