"""FRD from one record: bins, the sampled response, the quality indicator, refusals."""

from __future__ import annotations

import numpy as np
import pytest
from numpy.testing import assert_allclose
from scipy import signal

from commission.exceptions import IdentificationError
from commission.ident.frd import FRD, estimate_frd
from commission.ident.twomass import REFERENCE_PLANT, TwoMassParameters

FS = 8000.0


def chirp_torque(T: float = 10.0, fs: float = FS) -> np.ndarray:
    """METHOD.md excitation: linear chirp 0.1 → 400 Hz plus the 0.1 Hz bias."""
    A, f0, f1 = 0.0764, 0.1, 400.0
    t = np.arange(int(round(T * fs))) / fs
    return A * np.sin(2 * np.pi * (f0 * t + (f1 - f0) * t**2 / (2 * T))) + 3 * A * np.sin(2 * np.pi * 0.1 * t)


def sampled_velocity(p: TwoMassParameters, torque: np.ndarray, fs: float = FS, bits: int | None = 24) -> np.ndarray:
    """Exact linear plant: ZOH-discretised position, quantised, backward difference (from rest)."""
    J_m, J_l, B_m, B_l, K, D = p.as_array()
    A = np.array([[0, 0, 1, 0], [0, 0, 0, 1],
                  [-K / J_m, K / J_m, -(B_m + D) / J_m, D / J_m],
                  [K / J_l, -K / J_l, D / J_l, -(B_l + D) / J_l]])
    B = np.array([[0.0], [0.0], [1 / J_m], [0.0]])
    sys_d = signal.cont2discrete((A, B, np.array([[1.0, 0, 0, 0]]), np.zeros((1, 1))), 1 / fs, method="zoh")
    _, y, _ = signal.dlsim((*sys_d[:4], 1 / fs), torque)
    pos = y[:, 0]
    if bits:
        q = 2 * np.pi / 2**bits
        pos = np.round(pos / q) * q
    return np.diff(np.concatenate(([0.0], pos))) * fs


def exact_sampled_response(p: TwoMassParameters, f_hz: np.ndarray, fs: float = FS) -> np.ndarray:
    """Discrete V/T of the sampled plant: (1 − z⁻¹)/Ts · ZOH{P(s)/s}, evaluated on the unit circle."""
    num, den = p.velocity_tf()
    nd, dd, _ = signal.cont2discrete((num, np.concatenate([den, [0.0]])), 1 / fs, method="zoh")
    z = np.exp(2j * np.pi * f_hz / fs)
    return np.polyval(np.ravel(nd), z) / np.polyval(dd, z) * (1 - 1 / z) * fs


@pytest.fixture(scope="module")
def chirp_frd() -> tuple[np.ndarray, np.ndarray, FRD]:
    tq = chirp_torque()
    v = sampled_velocity(REFERENCE_PLANT, tq)
    return tq, v, estimate_frd(tq, v, FS)


def test_bins_and_fields(chirp_frd: tuple[np.ndarray, np.ndarray, FRD]) -> None:
    tq, v, frd = chirp_frd
    assert frd.frequency_hz.shape == (4000,)
    assert frd.frequency_hz[0] == pytest.approx(0.1)
    assert frd.frequency_hz[-1] == pytest.approx(400.0)
    assert frd.resolution_hz == pytest.approx(0.1)
    assert frd.sample_rate_hz == FS
    assert frd.n_samples == 80000
    for a in (frd.response, frd.input_dft, frd.output_dft, frd.quality):
        assert a.shape == (4000,)
    assert_allclose(frd.response, frd.output_dft / frd.input_dft)
    assert_allclose(frd.input_dft, np.fft.rfft(tq)[1:4001])


def test_quality_is_high_for_a_linear_plant(chirp_frd: tuple[np.ndarray, np.ndarray, FRD]) -> None:
    frd = chirp_frd[2]
    assert np.all((frd.quality >= 0.0) & (frd.quality <= 1.0))
    assert frd.quality.min() > 0.9999


def test_without_quality_the_rest_is_bit_identical(chirp_frd: tuple[np.ndarray, np.ndarray, FRD]) -> None:
    tq, v, frd = chirp_frd
    bare = estimate_frd(tq, v, FS, quality=False)
    assert np.isnan(bare.quality).all() and bare.quality.shape == frd.quality.shape
    for name in ("frequency_hz", "response", "input_dft", "output_dft"):
        np.testing.assert_array_equal(getattr(bare, name), getattr(frd, name))


def test_whole_record_ratio_is_biased(chirp_frd: tuple[np.ndarray, np.ndarray, FRD]) -> None:
    """Trap 1 of METHOD.md: the plain ratio is off by several % (transient), not just noise."""
    frd = chirp_frd[2]
    exact = exact_sampled_response(REFERENCE_PLANT, frd.frequency_hz)
    rel = np.abs(frd.response / exact - 1)
    band = (frd.frequency_hz > 0.3) & (frd.frequency_hz < 100)
    assert np.median(rel[band]) > 0.01


def test_periodic_steady_state_gives_the_sampled_response() -> None:
    """Independent check: a 10 s-periodic multisine, second period (transient decayed),
    gives exactly (1 − z⁻¹)/Ts·ZOH{P/s} — which the fit models as e^{−sTs}·sinc²·P."""
    n = 80000
    rng = np.random.default_rng(3)
    spec = np.zeros(n // 2 + 1, complex)
    spec[1:4001] = np.exp(2j * np.pi * rng.uniform(size=4000))
    period = np.fft.irfft(spec, n)
    period *= 0.05 / np.std(period)
    tq = np.tile(period, 2)
    v = sampled_velocity(REFERENCE_PLANT, tq, bits=None)
    frd = estimate_frd(tq[n:], v[n:], FS)
    exact = exact_sampled_response(REFERENCE_PLANT, frd.frequency_hz)
    assert_allclose(frd.response, exact, rtol=1e-5)
    f = frd.frequency_hz
    model = np.exp(-2j * np.pi * f / FS) * np.sinc(f / FS) ** 2 * REFERENCE_PLANT.velocity_response(f)
    assert np.max(np.abs(frd.response / model - 1)) < 1e-4      # aliasing terms ~ (f/fs)³


def test_band_and_resolution_options(chirp_frd: tuple[np.ndarray, np.ndarray, FRD]) -> None:
    tq, v, _ = chirp_frd
    frd = estimate_frd(tq, v, FS, band_hz=(10.0, 20.0), resolution_hz=0.5)
    assert frd.resolution_hz == pytest.approx(0.5)
    assert frd.frequency_hz[0] == pytest.approx(10.0)
    assert frd.frequency_hz[-1] == pytest.approx(20.0)
    assert frd.frequency_hz.size == 21


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        (dict(resolution_hz=0.05), "too short"),
        (dict(band_hz=(0.1, 4500.0)), "Nyquist"),
        (dict(band_hz=(100.03, 100.07)), "no DFT bin"),
        (dict(band_hz=(50.0, 20.0)), "no DFT bin"),
    ],
)
def test_refusals_of_options(chirp_frd: tuple[np.ndarray, np.ndarray, FRD], kwargs: dict, match: str) -> None:
    tq, v, _ = chirp_frd
    with pytest.raises(IdentificationError, match=match):
        estimate_frd(tq, v, FS, **kwargs)


def test_refuses_flat_input(chirp_frd: tuple[np.ndarray, np.ndarray, FRD]) -> None:
    _, v, _ = chirp_frd
    with pytest.raises(IdentificationError, match="does not excite"):
        estimate_frd(np.full(v.size, 0.1), v, FS)
    with pytest.raises(IdentificationError, match="does not excite"):
        estimate_frd(np.zeros(v.size), v, FS)


def test_refuses_flat_or_saturated_output(chirp_frd: tuple[np.ndarray, np.ndarray, FRD]) -> None:
    tq, v, _ = chirp_frd
    with pytest.raises(IdentificationError, match="constant"):
        estimate_frd(tq, np.zeros_like(tq), FS)
    with pytest.raises(IdentificationError, match="saturated"):
        estimate_frd(tq, np.clip(v, -10.0, 10.0), FS)


def test_refuses_bad_signals(chirp_frd: tuple[np.ndarray, np.ndarray, FRD]) -> None:
    tq, v, _ = chirp_frd
    with pytest.raises(IdentificationError, match="samples"):
        estimate_frd(tq[:-1], v, FS)
    bad = v.copy()
    bad[10] = np.nan
    with pytest.raises(IdentificationError, match="NaN"):
        estimate_frd(tq, bad, FS)
    with pytest.raises(IdentificationError, match="one-dimensional"):
        estimate_frd(tq.reshape(2, -1), v.reshape(2, -1), FS)


def test_quality_drops_with_backlash() -> None:
    plant = pytest.importorskip("sim_drive.plant")
    tq = chirp_torque()
    p = REFERENCE_PLANT.as_dict()
    q = {}
    for eps in (0.0, 0.4):
        r = plant.Plant(plant.PlantParameters(epsilon_deg=eps, **p), FS).run_torque(tq)
        q[eps] = estimate_frd(tq, r.motor_velocity, FS).quality
    assert q[0.0].min() > 0.9999
    # gear impacts are not explained by any smooth linear system (measured: min 0.990)
    assert q[0.4].min() < 0.998


def test_a_raised_band_is_the_full_frd_from_its_edge() -> None:
    # the hybrid start fits raised low band edges by slicing one FRD (start._bins) instead of
    # estimating each band again: every field must be the same, bin for bin (quality included)
    from commission.ident.start import _bins

    tq = chirp_torque()
    v = sampled_velocity(REFERENCE_PLANT, tq) + np.random.default_rng(2).normal(0.0, 1e-3, tq.size)
    full = estimate_frd(tq, v, FS, band_hz=(0.1, 400.0))
    for f_lo in (1.0, 5.0, 10.0):
        a = estimate_frd(tq, v, FS, band_hz=(f_lo, 400.0))
        b = _bins(full, full.frequency_hz >= f_lo - 1e-9 * full.resolution_hz)
        for k in ("frequency_hz", "response", "quality", "input_dft", "output_dft"):
            assert np.array_equal(getattr(a, k), getattr(b, k)), (f_lo, k)
