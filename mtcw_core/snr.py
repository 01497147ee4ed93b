"""Line signal-to-noise ratio of a coherent MTCW receiver: the dissertation's Eq. (5.11)/(5.12).

A *line* is the beat of the local oscillator (LO) with one optical component of the echo (the
echo carrier for the Doppler line at ``f_d``, a modulation sideband for a tone line at
``f_i +- f_d``). Its SNR in an electronic bandwidth ``df`` is the line's mean-square current over
the noise current variance in ``df``::

    SNR = <i_line^2> / sum_k <i_k^2>,   <i_line^2> = 2 * R^2 * G^2 * P_lo * P_line

(a line of amplitude ``A = 2*R*G*sqrt(P_lo*P_line)`` has mean square ``A^2/2``). The noise terms,
each a one-sided current power spectral density times ``df`` (A^2), derived from the optical
fields and square-law detection (the simulator draws them the same way, from fields, so the two
are independent checks of each other -- ``tests/test_snr.py``):

========== =============================================================== ==================
term       one-sided PSD (A^2/Hz)                                          receivers
========== =============================================================== ==================
thermal    ``4*k_B*T*F_n/R_L``                                             all
shot       ``2*q*I``, ``I = R*G*(P_lo + P_echo) + R*P_bb + I_dark``        all
           (``P_bb``: ASE and solar power reaching the detector)
RIN        ``RIN * (R*G*(P_lo + P_echo) + I_dark)^2``                      single only
sig-ASE    ``4*R^2*G*P_coh*S_ase`` for ``f < B_ase/2``                     all
ASE-ASE    ``4*R^2*S_ase^2*(B_ase - f)``                                   single only
sig-sun    ``4*R^2*G*P_coh*S_sun`` for ``f < B_sun/2``                     all
sun-sun    ``4*R^2*S_sun^2*(B_sun - f)``                                   single only
ASE-sun    ``8*R^2*S_ase*S_sun*overlap(f)``                                single only
========== =============================================================== ==================

``P_coh`` is the coherent light the broadband light beats with: the LO for a balanced receiver
(an ideal balanced detector cancels every direct-detection term: echo x ASE, ASE x ASE, sun x
sun, RIN), LO plus echo for a single photodiode. ``S`` is a per-polarisation power spectral
density (W/Hz) of unpolarised light at the detector, flat over an optical band ``B`` (Hz)
centred on the carrier; only the polarisation matching the LO beats with it, both
polarisations beat with themselves. The amplifier (gain ``G``, spontaneous-emission factor
``n_sp``) sits in front of the detector after LO and echo are combined, as in the
dissertation: it multiplies LO, echo and sunlight by ``G`` and adds ASE of
``S_ase = (G - 1)*n_sp*h*f0``. Sunlight through an optical filter of full width ``dlambda``:
``P_sun = SSI * A_rx * dlambda`` over ``B_sun = c*dlambda/lambda^2``, ``S_sun = G*P_sun/(2*B_sun)``
(Eq. 2.9's collected power). That counts every spatial mode the aperture collects as if it
beat with the LO, which is what the dissertation writes; for a single-mode (fibre) receiver
only one mode does, and an effective area ``rho*lambda^2/pi`` (Lambertian scene of reflectance
``rho``) gives the power in it -- see ``docs/snr.md``.

:func:`dissertation_eq_5_11` is the dissertation's formula as printed, kept for the comparison
(it uses the peak-squared signal ``4*R^2*G^2*P_lo*P_echo``, 3 dB above the mean square, and the
LO alone in the shot term). The chain's post-integration line SNR over a record of ``T``
seconds, ``N*A^2/(2*sigma^2)``, is :func:`line_snr` at ``df = 1/(2*T)``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

import numpy as np

from .phase import C

#: elementary charge (C), Boltzmann constant (J/K), Planck constant (J s): exact SI values
Q_E = 1.602176634e-19
K_B = 1.380649e-23
H_PLANCK = 6.62607015e-34

Receiver = Literal["single", "balanced"]


@dataclass(frozen=True)
class BroadbandLight:
    """Unpolarised broadband light at the detector.

    Attributes
    ----------
    psd_w_per_hz : float
        Power spectral density per polarisation (W/Hz), flat over the band.
    bandwidth_hz : float
        Full optical bandwidth (Hz), centred on the laser's carrier.
    """

    psd_w_per_hz: float
    bandwidth_hz: float

    @property
    def power_w(self) -> float:
        """Total power at the detector, both polarisations (W)."""
        return 2.0 * self.psd_w_per_hz * self.bandwidth_hz


def ase_light(gain: float, n_sp: float, wavelength_m: float, bandwidth_hz: float) -> BroadbandLight:
    """Amplified spontaneous emission of an amplifier of linear gain ``gain``.

    ``S_ase = (G - 1)*n_sp*h*f0`` per polarisation (W/Hz), ``f0 = c/wavelength``.

    Parameters
    ----------
    gain : float, linear power gain G >= 1
    n_sp : float, spontaneous-emission (population-inversion) factor >= 1
    wavelength_m : float, carrier wavelength (m)
    bandwidth_hz : float, optical band of the ASE reaching the detector (Hz)
    """
    if gain < 1 or n_sp < 1 or wavelength_m <= 0 or bandwidth_hz <= 0:
        raise ValueError("ase_light: need gain >= 1, n_sp >= 1, wavelength_m > 0, bandwidth_hz > 0")
    return BroadbandLight((gain - 1.0) * n_sp * H_PLANCK * C / wavelength_m, bandwidth_hz)


def optical_bandwidth_hz(filter_bandwidth_m: float, wavelength_m: float) -> float:
    """Frequency width (Hz) of an optical filter ``filter_bandwidth_m`` wide (m) at ``wavelength_m``:
    ``c*dlambda/lambda^2`` (600 GHz for 2 nm at 1 um)."""
    return C * filter_bandwidth_m / wavelength_m**2


def solar_light(spectral_irradiance_w_per_m2_nm: float, aperture_area_m2: float, filter_bandwidth_m: float,
                wavelength_m: float, gain: float = 1.0) -> BroadbandLight:
    """Sunlight collected by an aperture through an optical filter, after an amplifier of gain ``gain``.

    ``P_sun = SSI * A_rx * dlambda`` (the dissertation's Eq. 2.9 context), spread over the
    filter's band ``B = c*dlambda/lambda^2``; per polarisation ``S = G*P_sun/(2*B)``.

    Parameters
    ----------
    spectral_irradiance_w_per_m2_nm : float, SSI at the wavelength (W m^-2 nm^-1)
    aperture_area_m2 : float, receiver aperture (m^2) -- or the effective area of one spatial mode
    filter_bandwidth_m : float, full width of the optical filter (m); 2e-9 for +-1 nm
    wavelength_m : float, centre wavelength (m)
    gain : float, linear gain of an amplifier the sunlight passes through
    """
    if min(aperture_area_m2, filter_bandwidth_m, wavelength_m) <= 0 or spectral_irradiance_w_per_m2_nm < 0:
        raise ValueError("solar_light: need irradiance >= 0 and positive area, filter width and wavelength")
    p_w = spectral_irradiance_w_per_m2_nm * aperture_area_m2 * filter_bandwidth_m * 1e9
    b_hz = optical_bandwidth_hz(filter_bandwidth_m, wavelength_m)
    return BroadbandLight(gain * p_w / (2.0 * b_hz), b_hz)


@dataclass(frozen=True)
class SnrTerms:
    """Signal and noise current powers (A^2) of one line in an electronic bandwidth.

    Every attribute is a float or an array broadcast from the inputs of :func:`line_snr`.

    Attributes
    ----------
    signal_a2 : mean square of the line current
    thermal_a2, shot_a2, rin_a2 : detector and laser noise in the bandwidth
    sig_ase_a2, ase_ase_a2 : coherent light x ASE, ASE x ASE beat noise
    sig_sun_a2, sun_sun_a2, ase_sun_a2 : the same with sunlight, and ASE x sunlight
    """

    signal_a2: np.ndarray
    thermal_a2: np.ndarray
    shot_a2: np.ndarray
    rin_a2: np.ndarray
    sig_ase_a2: np.ndarray
    ase_ase_a2: np.ndarray
    sig_sun_a2: np.ndarray
    sun_sun_a2: np.ndarray
    ase_sun_a2: np.ndarray

    NOISE = ("thermal", "shot", "rin", "sig_ase", "ase_ase", "sig_sun", "sun_sun", "ase_sun")

    @property
    def noise_a2(self) -> np.ndarray:
        """Total noise current power in the bandwidth (A^2)."""
        return sum(getattr(self, f"{k}_a2") for k in self.NOISE)

    @property
    def snr(self) -> np.ndarray:
        """Linear SNR, signal over total noise."""
        return self.signal_a2 / self.noise_a2

    @property
    def snr_db(self) -> np.ndarray:
        return 10 * np.log10(self.snr)

    def terms_a2(self) -> dict[str, np.ndarray]:
        """Every noise term by name (A^2)."""
        return {k: getattr(self, f"{k}_a2") for k in self.NOISE}


def _overlap_hz(b1_hz: float, b2_hz: float, f_hz) -> np.ndarray:
    """Length of the intersection of bands of widths b1, b2 centred 0 and f apart (Hz)."""
    f = np.abs(np.asarray(f_hz, float))
    return np.maximum(0.0, np.minimum(b1_hz / 2, b2_hz / 2 + f) - np.maximum(-b1_hz / 2, -b2_hz / 2 + f))


def line_snr(
    p_lo_w, p_line_w, bandwidth_hz, *, p_echo_w=None, responsivity_a_per_w: float = 0.9,
    load_ohm: float = 50.0, temperature_k: float = 300.0, noise_figure: float = 1.0,
    dark_current_a: float = 0.0, rin_db_per_hz: float | None = None, gain: float = 1.0,
    ase: BroadbandLight | None = None, sun: BroadbandLight | None = None,
    receiver: Receiver = "balanced", line_frequency_hz=0.0,
) -> SnrTerms:
    """Signal and every noise term of one line (the dissertation's Eq. 5.11, from first principles).

    Powers are optical powers before the amplifier (the amplifier multiplies them by ``gain``);
    ``ase`` and ``sun`` are the broadband lights *at the detector* (:func:`ase_light`,
    :func:`solar_light` with the same gain). Array arguments broadcast.

    Parameters
    ----------
    p_lo_w : float or ndarray, LO power (W)
    p_line_w : float or ndarray
        Power of the echo's optical component that beats with the LO to make the line (W): the
        echo carrier for the Doppler line, one sideband for a tone line.
    bandwidth_hz : float or ndarray, electronic (filter) bandwidth around the line (Hz)
    p_echo_w : float or ndarray, optional
        Total echo power (W) for the shot, RIN and echo x broadband terms; default ``p_line_w``.
    responsivity_a_per_w, load_ohm, temperature_k, noise_figure, dark_current_a
        Detector: R (A/W), R_L (Ohm), T (K), linear noise figure F_n of the front end, I_dark (A).
    rin_db_per_hz : float, optional, laser RIN (dB/Hz); a balanced receiver cancels it
    gain : float, linear optical gain G of the amplifier in front of the detector (1: none)
    ase, sun : BroadbandLight, optional
    receiver : "single" or "balanced" (ideal: every direct-detection term cancels)
    line_frequency_hz : float or ndarray, the line's frequency (Hz); the broadband beat spectra
        fall off with it (flat far below the optical bands)

    Returns
    -------
    SnrTerms

    Raises
    ------
    ValueError
        For an unknown receiver (an IQ receiver is not modelled here) or a non-positive bandwidth.
    """
    if receiver not in ("single", "balanced"):
        raise ValueError(f"receiver: {receiver!r} is not modelled (single | balanced)")
    df = np.asarray(bandwidth_hz, float)
    if np.any(df <= 0):
        raise ValueError("bandwidth_hz: must be > 0")
    r = responsivity_a_per_w
    p_lo = np.asarray(p_lo_w, float)
    p_line = np.asarray(p_line_w, float)
    p_echo = p_line if p_echo_w is None else np.asarray(p_echo_w, float)
    f = np.asarray(line_frequency_hz, float)
    single = receiver == "single"
    zero = np.zeros(np.broadcast(p_lo, p_line, p_echo, df, f).shape)

    signal = 2 * r**2 * gain**2 * p_lo * p_line + zero
    thermal = 4 * K_B * temperature_k * noise_figure / load_ohm * df + zero
    p_bb = sum(b.power_w for b in (ase, sun) if b is not None)
    i_laser = r * gain * (p_lo + p_echo) + dark_current_a
    shot = 2 * Q_E * (i_laser + r * p_bb) * df + zero
    rin = zero if rin_db_per_hz is None or not single else 10 ** (rin_db_per_hz / 10) * i_laser**2 * df + zero
    # the coherent light that beats with broadband light: the LO, plus the echo on a single PD
    p_coh = gain * (p_lo + (p_echo if single else 0.0))

    def sig_x(b: BroadbandLight | None):
        if b is None:
            return zero
        return 4 * r**2 * p_coh * b.psd_w_per_hz * (f < b.bandwidth_hz / 2) * df + zero

    def x_x(a: BroadbandLight | None, b: BroadbandLight | None, factor: float):
        if a is None or b is None or not single:
            return zero
        return factor * r**2 * a.psd_w_per_hz * b.psd_w_per_hz * _overlap_hz(a.bandwidth_hz, b.bandwidth_hz, f) * df + zero

    return SnrTerms(signal, thermal, shot, rin, sig_x(ase), x_x(ase, ase, 4.0), sig_x(sun), x_x(sun, sun, 4.0),
                    x_x(ase, sun, 8.0))


def dissertation_eq_5_11(
    p_lo_w, p_echo_w, bandwidth_hz, *, responsivity_a_per_w: float, load_ohm: float, temperature_k: float,
    gain: float, n_sp: float, wavelength_m: float, ase_bandwidth_hz: float, solar_power_w: float,
    solar_bandwidth_hz: float,
) -> np.ndarray:
    """The dissertation's Eq. (5.11) as printed (linear SNR), for the comparison in ``docs/snr.md``.

    ``SNR = 4 R^2 G^2 P_lo P_echo / (4 k_B T df/R_L + 2 q G R P_lo df + 4 G R^2 P_lo S_sp df
    + 4 R^2 S_sp^2 df df_opt + 4 G^2 R^2 P_lo S_solar df + 4 G^2 R^2 S_solar^2 df df_opt)`` with
    ``S_sp = (G - 1) n_sp h f0`` and ``S_solar = P_sun/df_opt`` (the collected solar power per Hz).
    """
    r, g, df = responsivity_a_per_w, gain, np.asarray(bandwidth_hz, float)
    s_sp = (g - 1) * n_sp * H_PLANCK * C / wavelength_m
    s_sol = solar_power_w / solar_bandwidth_hz
    noise = (4 * K_B * temperature_k / load_ohm * df + 2 * Q_E * g * r * p_lo_w * df
             + 4 * g * r**2 * p_lo_w * s_sp * df + 4 * r**2 * s_sp**2 * df * ase_bandwidth_hz
             + 4 * g**2 * r**2 * p_lo_w * s_sol * df + 4 * g**2 * r**2 * s_sol**2 * df * solar_bandwidth_hz)
    return 4 * r**2 * g**2 * np.asarray(p_lo_w) * np.asarray(p_echo_w) / noise


def dissertation_eq_5_12(p_echo_w, bandwidth_hz, *, responsivity_a_per_w: float, gain: float) -> np.ndarray:
    """The dissertation's shot-noise limit, Eq. (5.12): ``SNR = 2 R G P_echo/(q df)`` (linear)."""
    return 2 * responsivity_a_per_w * gain * np.asarray(p_echo_w) / (Q_E * np.asarray(bandwidth_hz, float))


@dataclass(frozen=True)
class Link:
    """One SNR-against-attenuation curve's parameters; the defaults are the dissertation's Fig. 36.

    Fig. 36 states P_LO 5 mW, echo 10 mW before attenuation, 300 K, 3 dB gain, sunlight at 1 um
    through a +-1 nm filter; the rest is not stated there and is assumed here (``docs/snr.md``):
    a balanced receiver (Eq. 5.11 assumes one), R = 0.7 A/W (0.9 A/W, the dissertation's
    1550 nm detector, would be a quantum efficiency of 1.12 at 1 um), 50 Ohm, F_n = 1, 1.5 nA dark
    current (the dissertation's PIN), n_sp = 1.5, the ASE through the same 2 nm filter, solar
    spectral irradiance 0.75 W m^-2 nm^-1 and ``aperture_area_m2`` None: one spatial mode of a
    white sunlit Lambertian scene, ``lambda^2/pi`` (what a single-mode receiver's LO can beat with).
    """

    wavelength_m: float = 1.0e-6
    p_lo_w: float = 5e-3
    p_echo_w: float = 10e-3
    temperature_k: float = 300.0
    gain_db: float = 3.0
    n_sp: float = 1.5
    responsivity_a_per_w: float = 0.7
    load_ohm: float = 50.0
    noise_figure: float = 1.0
    dark_current_a: float = 1.5e-9
    rin_db_per_hz: float | None = None
    solar_irradiance_w_per_m2_nm: float = 0.75
    aperture_area_m2: float | None = None
    filter_bandwidth_m: float = 2e-9
    receiver: Receiver = "balanced"

    @property
    def gain(self) -> float:
        return 10 ** (self.gain_db / 10)

    @property
    def area_m2(self) -> float:
        """The solar collection area (m^2): as given, else ``lambda^2/pi`` (one mode, white scene)."""
        return self.wavelength_m**2 / math.pi if self.aperture_area_m2 is None else self.aperture_area_m2

    @property
    def optical_bandwidth_hz(self) -> float:
        return optical_bandwidth_hz(self.filter_bandwidth_m, self.wavelength_m)

    def ase(self) -> BroadbandLight | None:
        return ase_light(self.gain, self.n_sp, self.wavelength_m, self.optical_bandwidth_hz) if self.gain > 1 else None

    def sun(self) -> BroadbandLight | None:
        if self.solar_irradiance_w_per_m2_nm <= 0:
            return None
        return solar_light(self.solar_irradiance_w_per_m2_nm, self.area_m2, self.filter_bandwidth_m,
                           self.wavelength_m, self.gain)

    def terms(self, attenuation_db, bandwidth_hz, line_fraction: float = 1.0, line_frequency_hz=0.0) -> SnrTerms:
        """:func:`line_snr` of the line whose optical component is ``line_fraction`` of the echo.

        Parameters
        ----------
        attenuation_db : float or ndarray, echo attenuation (dB); broadcasts with ``bandwidth_hz``
        bandwidth_hz : float or ndarray, electronic bandwidth around the line (Hz)
        line_fraction : float, share of the echo power in the component beating with the LO
            (1: the whole echo, as Fig. 36; ``m^2/16`` for one sideband of a small-signal MZM tone)
        """
        p_echo = self.p_echo_w * 10 ** (-np.asarray(attenuation_db, float) / 10)
        return line_snr(self.p_lo_w, line_fraction * p_echo, bandwidth_hz, p_echo_w=p_echo,
                        responsivity_a_per_w=self.responsivity_a_per_w, load_ohm=self.load_ohm,
                        temperature_k=self.temperature_k, noise_figure=self.noise_figure,
                        dark_current_a=self.dark_current_a, rin_db_per_hz=self.rin_db_per_hz, gain=self.gain,
                        ase=self.ase(), sun=self.sun(), receiver=self.receiver, line_frequency_hz=line_frequency_hz)

    def dissertation(self, attenuation_db, bandwidth_hz) -> np.ndarray:
        """The dissertation's Eq. (5.11) as printed, same parameters (linear SNR)."""
        sun = self.sun()
        p_sun = 0.0 if sun is None else sun.power_w / self.gain
        p_echo = self.p_echo_w * 10 ** (-np.asarray(attenuation_db, float) / 10)
        return dissertation_eq_5_11(self.p_lo_w, p_echo, bandwidth_hz, responsivity_a_per_w=self.responsivity_a_per_w,
                                    load_ohm=self.load_ohm, temperature_k=self.temperature_k, gain=self.gain,
                                    n_sp=self.n_sp, wavelength_m=self.wavelength_m,
                                    ase_bandwidth_hz=self.optical_bandwidth_hz, solar_power_w=p_sun,
                                    solar_bandwidth_hz=self.optical_bandwidth_hz)


__all__ = ["Q_E", "K_B", "H_PLANCK", "BroadbandLight", "ase_light", "solar_light", "optical_bandwidth_hz",
           "SnrTerms", "line_snr", "dissertation_eq_5_11", "dissertation_eq_5_12", "Link"]
