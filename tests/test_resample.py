"""Host-streamed recordings (jittered SYNC times) are identified on the nominal grid.

The streamed situation is built exactly: the drive runs its 8 kHz ticks, the
host's SYNC arrives every 4 ticks ± 1 (2 kHz nominal, 125 µs jitter), the target
torque is held from one SYNC to the next, and the feedback is latched at SYNC.
"""

import math

import numpy as np
import pytest

from commission.config import Config
from commission.exceptions import IdentificationError
from commission.excitation import chirp
from commission.ident.hybrid import identify
from commission.ident.resample import to_uniform
from commission.recording import Recording
from sim_drive.plant import Plant, PlantParameters

TRUE = PlantParameters(seed=1, torque_noise_nm=1e-4)


def streamed(jitter_ticks: int, seed: int = 0) -> Recording:
    w = chirp(Config().excitation).samples
    rng = np.random.default_rng(seed)
    gaps = 4 + rng.integers(-jitter_ticks, jitter_ticks + 1, size=w.size // 3)
    ticks = np.concatenate(([0], np.cumsum(gaps)))
    ticks = ticks[ticks < w.size]
    target = w[ticks]
    r = Plant(TRUE).run_torque(np.repeat(target, np.diff(np.append(ticks, w.size))))
    return Recording(t=ticks / 8000.0, sample_rate_hz=2000.0, torque_ref=target,
                     motor_velocity=r.motor_velocity[ticks], motor_position=r.motor_position[ticks])


def test_resampling_keeps_the_torque_impulse_and_reports_the_jitter():
    rec = streamed(1)
    uni, info = to_uniform(rec)
    assert uni.is_uniform and uni.sample_rate_hz == 2000.0
    assert 80e-6 < info.jitter_rms_s < 125e-6 and info.jitter_max_s == pytest.approx(125e-6)
    # ∫τ dt over the whole run is the same on both grids (up to the last partial period)
    impulse_in = np.sum(rec.torque_ref[:-1] * np.diff(rec.t))
    impulse_out = np.sum(uni.torque_ref[:-1]) / 2000.0
    assert impulse_out == pytest.approx(impulse_in, abs=2e-4)


@pytest.mark.parametrize("jitter, tol_j, tol_jm, tol_eps_deg", [(0, 0.002, 0.002, 0.002), (1, 0.01, 0.05, 0.01)])
def test_streamed_run_identifies(jitter, tol_j, tol_jm, tol_eps_deg):
    res = identify(streamed(jitter))
    p = res.parameters
    assert p.J_m == pytest.approx(TRUE.J_m, rel=tol_jm)
    assert p.J_l == pytest.approx(TRUE.J_l, rel=tol_j)
    assert p.K == pytest.approx(TRUE.K, rel=tol_j)
    assert res.epsilon_deg == pytest.approx(0.40, abs=tol_eps_deg)
    assert any("jitter" in n for n in res.notes) is (jitter > 0)


def test_a_long_gap_in_the_sample_times_is_refused():
    rec = streamed(0)
    t = rec.t.copy()
    t[5000:] += 0.05  # 50 ms without a SYNC
    with pytest.raises(IdentificationError, match="gap of 50.5 ms at sample 5000"):
        identify(rec.replace(t=t))
    assert math.isfinite(rec.t[-1])
