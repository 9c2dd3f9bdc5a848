"""Frequency-response data (FRD) of one torque → motor-velocity experiment (step 2).

One DFT of the whole record at its resolution 1/T, no window (a window would cut away the
chirp's ends). The ratio ``response = Y/U`` (the paper's FRD) is biased by a few percent, since
the record is not periodic (the output DFT carries a transient the input's does not), and holds
the sampling delay; so :class:`FRD` also carries the raw DFTs, which
:func:`commission.ident.tffit.fit_transfer_function` fits with both modelled.

DFT convention: ``X[k] = Σ_{n=0}^{N−1} x[n]·exp(−2πj·k·n/N)`` (numpy's
unnormalised FFT), bin k at ``k·fs/N`` Hz, N = round(fs/resolution).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray
from threadpoolctl import threadpool_limits

from commission.exceptions import IdentificationError

#: Half-width (bins) and polynomial degree of the local model behind ``quality``.
_LPM_HALF_WIDTH = 4
_LPM_DEGREE = 2


@dataclass(frozen=True)
class FRD:
    """Frequency-response data V_m/T_ref at the DFT bins inside the band.

    ``quality`` is a one-record substitute for the coherence (a single record has no
    repetitions): the local polynomial method (Pintelon & Schoukens) fits Y as G(k)·U + T(k)
    within ±4 bins, G and the transient T quadratic in the bin offset; the residual σ² is what
    no smooth linear system explains (noise, quantisation, gear impacts), and
    ``quality = S/(S + σ²)``, S the mean |Y|² in the window, like γ² = SNR/(1 + SNR).
    """

    frequency_hz: NDArray[np.float64]  # (M,) bin frequencies inside the band [Hz]
    response: NDArray[np.complex128]  # (M,) the plain ratio Y/U [rad/s per N·m] (biased)
    quality: NDArray[np.float64]  # (M,) in [0, 1]; NaN when not computed (quality=False)
    input_dft: NDArray[np.complex128]  # (M,) DFT of the torque reference [N·m] (unnormalised)
    output_dft: NDArray[np.complex128]  # (M,) DFT of the motor velocity [rad/s] (unnormalised)
    sample_rate_hz: float  # [Hz]
    resolution_hz: float  # bin spacing sample_rate_hz / N [Hz], N the samples transformed

    @property
    def n_samples(self) -> int:
        """Number of samples N that were transformed."""
        return int(round(self.sample_rate_hz / self.resolution_hz))


def _as_signal(x: ArrayLike, name: str) -> NDArray[np.float64]:
    a = np.asarray(x, dtype=float)
    if a.ndim != 1:
        raise IdentificationError(f"{name} must be one-dimensional, got shape {a.shape}")
    if not np.all(np.isfinite(a)):
        raise IdentificationError(f"{name} contains NaN or infinite samples")
    return a


def _longest_run(mask: NDArray[np.bool_]) -> int:
    if not mask.any():
        return 0
    m = np.concatenate(([0], mask.astype(np.int8), [0]))
    d = np.diff(m)
    starts, ends = np.flatnonzero(d == 1), np.flatnonzero(d == -1)
    return int((ends - starts).max())


def _local_quality(U: NDArray[np.complex128], Y: NDArray[np.complex128],
                   bins: NDArray[np.int_]) -> NDArray[np.float64]:
    """Local-polynomial-method quality at ``bins`` of the full one-sided spectra U, Y."""
    R, deg = _LPM_HALF_WIDTH, _LPM_DEGREE
    n_bins = U.size
    # window centres clamped so that the window stays inside [1, n_bins − 1]
    centres = np.clip(bins, 1 + R, n_bins - 1 - R)
    r = np.arange(-R, R + 1)
    idx = centres[:, None] + r[None, :]                      # (M, W)
    offs = (bins[:, None] - centres[:, None]) + r[None, :]   # offsets relative to the bin itself
    powers = offs[..., None].astype(float) ** np.arange(deg + 1)  # (M, W, deg+1)
    Uw, Yw = U[idx], Y[idx]
    scale_u = np.sqrt(np.mean(np.abs(Uw) ** 2, axis=1, keepdims=True)) + 1e-300
    A = np.concatenate([powers * (Uw / scale_u)[..., None], powers.astype(complex)], axis=2)
    # residual of the least-squares fit: (I − Q·Qᴴ)·y, batched QR (A has full column
    # rank: the transient columns are a Vandermonde block, U ≠ 0 in the band)
    Q = np.linalg.qr(A)[0]
    e = Yw - np.einsum("mwp,mp->mw", Q, np.einsum("mwp,mw->mp", Q.conj(), Yw))
    dof = A.shape[1] - A.shape[2]
    sigma2 = np.sum(np.abs(e) ** 2, axis=1) / dof
    S = np.mean(np.abs(Yw) ** 2, axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        q = S / (S + sigma2)
    return np.clip(np.nan_to_num(q, nan=0.0), 0.0, 1.0)


def estimate_frd(torque_ref: ArrayLike, motor_velocity: ArrayLike, sample_rate_hz: float, *,
                 band_hz: tuple[float, float] = (0.1, 400.0), resolution_hz: float = 0.1,
                 quality: bool = True) -> FRD:
    """FRD of V_m/T_ref from one record, at ``resolution_hz`` inside ``band_hz``.

    The first N = round(fs/resolution_hz) samples are transformed (the whole
    record for the standard 10 s experiment at 0.1 Hz). Both ends of the band
    are inclusive.

    :param torque_ref: torque reference [N·m], one sample per tick.
    :param motor_velocity: motor velocity [rad/s] of the same ticks
        (v[k] = (x[k] − x[k−1])/Ts, the drive's convention).
    :param quality: compute :attr:`FRD.quality` (most of this function's time); False: NaN,
        for FRDs that are only compared or fitted.
    :raises IdentificationError: the signals have different lengths or
        non-finite samples; the record is shorter than 1/resolution_hz; the
        band reaches above Nyquist or holds no bin; the torque does not excite
        the band; the velocity is flat, saturated or silent in the band.
    """
    u = _as_signal(torque_ref, "torque_ref")
    y = _as_signal(motor_velocity, "motor_velocity")
    fs = float(sample_rate_hz)
    if not (np.isfinite(fs) and fs > 0.0):
        raise IdentificationError(f"sample rate {sample_rate_hz!r} Hz is not a positive number")
    if u.size != y.size:
        raise IdentificationError(f"torque_ref has {u.size} samples but motor_velocity has {y.size}")
    if not (np.isfinite(resolution_hz) and resolution_hz > 0.0):
        raise IdentificationError(f"resolution {resolution_hz!r} Hz is not a positive number")
    n = int(round(fs / resolution_hz))
    if u.size < n:
        raise IdentificationError(
            f"record of {u.size / fs:.3f} s is too short for a {resolution_hz:g} Hz resolution "
            f"(needs {n} samples = {n / fs:.3f} s)"
        )
    f_lo, f_hi = float(band_hz[0]), float(band_hz[1])
    nyquist = fs / 2.0
    if f_hi > nyquist:
        raise IdentificationError(f"band upper edge {f_hi:g} Hz is above Nyquist ({nyquist:g} Hz)")
    df = fs / n
    tol = 1e-9 * df
    k_lo = max(1, int(np.ceil((f_lo - tol) / df)))
    k_hi = int(np.floor((f_hi + tol) / df))
    if not (f_lo < f_hi) or k_hi < k_lo:
        raise IdentificationError(f"band {f_lo:g}–{f_hi:g} Hz holds no DFT bin at {df:g} Hz resolution")
    u, y = u[:n], y[:n]

    # output: flat or saturated (clipped at a limit for a stretch of ≥ 1 % of the record)
    ptp = float(np.ptp(y))
    if ptp == 0.0:
        raise IdentificationError("motor_velocity is constant: the motor did not move")
    run = max(_longest_run(y == y.max()), _longest_run(y == y.min()))
    if run >= max(10, n // 100):
        raise IdentificationError(
            f"motor_velocity sits at its extreme value for {run} consecutive samples "
            f"({run / fs * 1e3:.1f} ms): saturated or clipped"
        )

    U = np.fft.rfft(u)
    Y = np.fft.rfft(y)
    bins = np.arange(k_lo, k_hi + 1)
    Ub, Yb = U[bins], Y[bins]
    total_u = float(np.sum(np.abs(U[1:]) ** 2))
    band_u = float(np.sum(np.abs(Ub) ** 2))
    if total_u == 0.0 or band_u <= 1e-12 * (total_u + abs(U[0]) ** 2):
        raise IdentificationError(
            f"torque_ref does not excite the band {f_lo:g}–{f_hi:g} Hz (flat or out-of-band input)"
        )
    if np.any(np.abs(Ub) == 0.0):
        k0 = bins[np.flatnonzero(np.abs(Ub) == 0.0)[0]]
        raise IdentificationError(f"torque_ref has no energy at {k0 * df:g} Hz inside the band")
    total_y = float(np.sum(np.abs(Y[1:]) ** 2))
    if float(np.sum(np.abs(Yb) ** 2)) <= 1e-12 * total_y:
        raise IdentificationError(f"motor_velocity has no energy in the band {f_lo:g}–{f_hi:g} Hz")
    if quality:
        with threadpool_limits(limits=1, user_api="blas"):  # many tiny problems
            q = _local_quality(U, Y, bins)
    else:
        q = np.full(bins.size, np.nan)
    return FRD(frequency_hz=bins * df, response=Yb / Ub, quality=q, input_dft=Ub, output_dft=Yb,
               sample_rate_hz=fs, resolution_hz=df)
