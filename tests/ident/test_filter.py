"""The identification filter without scipy.signal (stagectl.ident._filter), checked against scipy.signal itself:
the same Butterworth sections (frequency response) and the same zero-phase output, padding and start-up
included, to rounding."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import signal

from stagectl.ident._filter import butter_lowpass_sos, sosfiltfilt


@pytest.mark.parametrize("order,wn", [(4, 0.2), (4, 0.02), (3, 0.3), (2, 0.9), (5, 0.05)])
def test_butterworth_and_zero_phase_filter_equal_scipy(order: int, wn: float) -> None:
    ref = signal.butter(order, wn, output="sos")
    sos = butter_lowpass_sos(order, wn)
    _, h_ref = signal.sosfreqz(ref, 256)
    _, h = signal.sosfreqz(sos, 256)
    assert np.max(np.abs(h - h_ref)) < 1e-12
    x = np.random.default_rng(order).standard_normal((2000, 3)).cumsum(axis=0)  # a drifting signal: padding
    y_ref = signal.sosfiltfilt(ref, x, axis=0)                                  # and start-up matter
    assert np.max(np.abs(sosfiltfilt(sos, x, axis=0) - y_ref)) < 1e-9 * np.max(np.abs(y_ref))
    assert np.max(np.abs(sosfiltfilt(sos, x[:, 1]) - y_ref[:, 1])) < 1e-9 * np.max(np.abs(y_ref))


def test_bad_arguments_are_refused() -> None:
    with pytest.raises(ValueError, match="wn"):
        butter_lowpass_sos(4, 1.0)
    with pytest.raises(ValueError, match="longer than the padding"):
        sosfiltfilt(butter_lowpass_sos(4, 0.2), np.zeros(10))


@pytest.mark.parametrize("k", [1, 2, 3, 6])
def test_fast_two_section_path_is_bit_identical_to_the_general_cascade(k: int) -> None:
    """The 4th-order filter of discovery runs two signals at a time with its states in registers
    (_filtfilt_rows2); it must give the general cascade's result bit for bit (discovery's results do not
    move), for an odd signal run alone too, with the stuck samples zeroed as np.where would."""
    from stagectl.ident._filter import _edge, _filtfilt_cols, _zi, filtfilt_rows

    sos = butter_lowpass_sos(4, 0.1)
    rng = np.random.default_rng(k)
    x = rng.standard_normal((k, 3000)).cumsum(axis=1)
    mask = rng.random(3000) > 0.2
    general = _filtfilt_cols(sos, _zi(sos), np.ascontiguousarray(np.where(mask, x, 0.0).T), _edge(sos)).T
    assert np.array_equal(filtfilt_rows(sos, x, mask), general)
    assert np.array_equal(filtfilt_rows(sos, x), _filtfilt_cols(sos, _zi(sos), np.ascontiguousarray(x.T),
                                                                _edge(sos)).T)
