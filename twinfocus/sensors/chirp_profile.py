"""The chirp a capture was taken with, from its configuration: TI's chirp profile -> :class:`Chirp`.

Every TI configuration form describes the chirp by the same ``rlProfileCfg_t`` quantities
(mmwavelink): start frequency (GHz), idle time (us), ADC start time (us), ramp end time (us),
slope (MHz/us), ADC samples, ADC sample rate (ksps). The forms read here:

- mmWave Studio JSON (``*.mmwave.json``): ``mmWaveDevices[d].rfConfig.rlProfiles[i].rlProfileCfg_t``
  with ``startFreqConst_GHz``, ``idleTimeConst_usec``, ``adcStartTimeConst_usec``,
  ``rampEndTime_usec``, ``freqSlopeConst_MHz_usec``, ``numAdcSamples``, ``digOutSampleRate`` (ksps);
- mmWave Studio Lua: ``ar1.ProfileConfig(profileId, startFreq, idleTime, adcStartTime, rampEndTime,
  tx0PowerBackoff, tx1PowerBackoff, tx2PowerBackoff, tx0PhaseShifter, tx1PhaseShifter,
  tx2PhaseShifter, freqSlope, txStartTime, numAdcSamples, sampleRate, hpfCornerFreq1,
  hpfCornerFreq2, rxGain)`` (18 arguments, the order of mmwavelink's ``rlProfileCfg_t`` with the
  three TX backoffs and phase shifters spelled out), and the cascade form
  ``ar1.ProfileConfig_mult`` with the device map first, as mmWave Studio's
  ``Scripts/Cascade/Cascade_Configuration_MIMO.lua`` calls it:
  ``ar1.ProfileConfig_mult(deviceMapOverall, 0, start_freq, idle_time, adc_start_time,
  ramp_end_time, 0, 0, 0, 0, 0, 0, slope, 0, adc_samples, sample_freq, 0, 0, rx_gain)`` with the
  script's ``local start_freq = 77 -- GHz`` ... ``local sample_freq = 8000 -- ksps``;
- mmWave SDK ``.cfg`` ``profileCfg`` (:mod:`twinfocus.sensors.ti_cli`).

The first ADC sample is taken ``adcStartTime`` after the ramp starts, so the chirp's ``f0_hz``
is ``startFreq + slope * adcStartTime`` (TI's ``module_param.m`` takes the carrier as
``startFreqConst + (adcStartTimeConst + rampTime / 2) * slope`` the same way).
"""

from __future__ import annotations

import dataclasses
import re
from dataclasses import dataclass

from twinfocus.errors import TwinFocusError
from twinfocus.radar.fmcw import Chirp


@dataclass(frozen=True)
class Profile:
    """One TI chirp profile in TI's units (GHz, us, MHz/us, ksps); idle and ramp end may be
    unknown (None) where a configuration does not give them."""

    start_freq_ghz: float
    idle_time_us: float | None
    adc_start_time_us: float
    ramp_end_time_us: float | None
    slope_mhz_per_us: float
    n_samples: int
    sample_rate_ksps: float

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)


#: The project's default chirp (:class:`Chirp`'s defaults) as a profile: 76 GHz, 5 us ADC start,
#: 120 MHz/us, 256 samples at 8 Msps.
DEFAULT_PROFILE = Profile(76.0, None, 5.0, None, 120.0, 256, 8000.0)

#: The profile fields and the option of ``twinfocus convert`` that overrides each chirp quantity.
_OPTION_OF = {"f0_hz": "--f0-hz", "slope_hz_per_s": "--slope-hz-per-s", "fs_hz": "--fs-hz", "n_samples": "--n-samples"}


def profile_chirp(p: Profile) -> Chirp:
    """The sampled chirp of a profile: first ADC sample at start + slope x ADC start time."""
    slope = float(p.slope_mhz_per_us) * 1e12
    return Chirp(
        f0_hz=float(p.start_freq_ghz) * 1e9 + slope * float(p.adc_start_time_us) * 1e-6,
        slope_hz_per_s=slope,
        fs_hz=float(p.sample_rate_ksps) * 1e3,
        n_samples=int(p.n_samples),
    )


def check_profile(p: Profile, source: str) -> None:
    """Refuse a profile whose numbers cannot describe a chirp, or whose sampling runs past the
    ramp (ADC start + samples / rate > ramp end: the last samples would not be on the ramp)."""
    for name in ("start_freq_ghz", "adc_start_time_us", "slope_mhz_per_us", "sample_rate_ksps"):
        v = float(getattr(p, name))
        if not v == v or v < 0 or (v == 0 and name != "adc_start_time_us"):
            raise TwinFocusError(f"{source}: chirp profile {name} = {v:g} is not a usable value")
    if int(p.n_samples) < 2:
        raise TwinFocusError(f"{source}: chirp profile has {p.n_samples} ADC samples; at least 2 are needed")
    if p.ramp_end_time_us is not None:
        end_us = float(p.adc_start_time_us) + int(p.n_samples) / float(p.sample_rate_ksps) * 1e3
        if end_us > float(p.ramp_end_time_us) * (1 + 1e-6):
            raise TwinFocusError(
                f"{source}: the ADC samples until {end_us:g} us (start {p.adc_start_time_us:g} us + "
                f"{p.n_samples} samples at {p.sample_rate_ksps:g} ksps) but the ramp ends at {p.ramp_end_time_us:g} us"
            )


def _num(v) -> float:
    if isinstance(v, str) and v.strip().lower().startswith("0x"):
        return float(int(v, 16))
    return float(v)


#: rlProfileCfg_t keys of the mmWave Studio JSON -> Profile fields.
_JSON_KEYS = {
    "startFreqConst_GHz": "start_freq_ghz",
    "idleTimeConst_usec": "idle_time_us",
    "adcStartTimeConst_usec": "adc_start_time_us",
    "rampEndTime_usec": "ramp_end_time_us",
    "freqSlopeConst_MHz_usec": "slope_mhz_per_us",
    "numAdcSamples": "n_samples",
    "digOutSampleRate": "sample_rate_ksps",
}


def profile_fields_from_studio_json(rf_config: dict, profile_id: int | None = None) -> dict:
    """The profile fields one device's ``rfConfig`` gives (only those present).

    rf_config : ``mmWaveDevices[d].rfConfig``; profile_id : the profile the frame's chirps use
    (None: the first profile). Returns {Profile field: value}.
    """
    profiles = [p.get("rlProfileCfg_t", p) for p in rf_config["rlProfiles"]]
    if not profiles:
        raise KeyError("rlProfiles is empty")
    chosen = profiles[0]
    if profile_id is not None:
        hits = [p for p in profiles if int(_num(p.get("profileId", 0))) == int(profile_id)]
        if not hits:
            raise TwinFocusError(f"the chirps use profile {profile_id} but rlProfiles does not define it")
        chosen = hits[0]
    out: dict = {}
    for key, name in _JSON_KEYS.items():
        if key in chosen:
            v = _num(chosen[key])
            out[name] = int(v) if name == "n_samples" else v
    return out


_LUA_PROFILE_CALL = re.compile(r"\bar1\.ProfileConfig(_mult)?\s*\(([^()]*)\)")
_LUA_NUMBER_ASSIGN = re.compile(
    r"^\s*(?:local\s+)?([A-Za-z_]\w*)\s*=\s*([-+]?[0-9.]+(?:[eE][-+]?\d+)?)\s*(?:--.*)?$", re.M
)
#: Argument positions of ar1.ProfileConfig (without the _mult device map) -> Profile fields.
_LUA_ARGS = {
    1: "start_freq_ghz",
    2: "idle_time_us",
    3: "adc_start_time_us",
    4: "ramp_end_time_us",
    11: "slope_mhz_per_us",
    13: "n_samples",
    14: "sample_rate_ksps",
}
_LUA_N_ARGS = 18


def profile_fields_from_lua(text: str, source: str) -> dict:
    """The profile of a mmWave Studio Lua script's ``ar1.ProfileConfig`` / ``ar1.ProfileConfig_mult``
    call ({} when it has none); arguments that are variables are looked up in the script's numeric
    assignments. Comments must already be stripped. Several different profiles are refused."""
    values = {k: float(v) for k, v in _LUA_NUMBER_ASSIGN.findall(text)}
    found: list[dict] = []
    for m in _LUA_PROFILE_CALL.finditer(text):
        args = [a.strip() for a in m.group(2).split(",")]
        if m.group(1):
            args = args[1:]  # the device map
        if len(args) != _LUA_N_ARGS:
            raise TwinFocusError(
                f"{source}: ar1.ProfileConfig{m.group(1) or ''} has {len(args)} profile arguments, the "
                f"{_LUA_N_ARGS}-argument form (profileId, startFreq, idleTime, adcStartTime, rampEndTime, 3 TX "
                "backoffs, 3 TX phase shifters, slope, txStartTime, numAdcSamples, sampleRate, hpf1, hpf2, rxGain) is read"
            )
        fields = {}
        for pos, name in _LUA_ARGS.items():
            a = args[pos]
            try:
                v = float(a)
            except ValueError:
                if a not in values:
                    raise TwinFocusError(
                        f"{source}: ar1.ProfileConfig argument {a!r} ({name}) is neither a number nor a variable "
                        "the script sets to one"
                    ) from None
                v = values[a]
            fields[name] = int(v) if name == "n_samples" else v
        if fields not in found:
            found.append(fields)
    if len(found) > 1:
        raise TwinFocusError(f"{source}: {len(found)} different chirp profiles; only a single-profile capture is read")
    return found[0] if found else {}


def resolve_chirp(
    fields: dict,
    source: str | None,
    f0_hz: float | None = None,
    slope_hz_per_s: float | None = None,
    fs_hz: float | None = None,
    n_samples: int | None = None,
) -> tuple[Chirp, Profile, list[str]]:
    """The chirp of a capture: its configuration's profile ``fields`` (what it gives, the rest
    from :data:`DEFAULT_PROFILE`), then the options, each of which wins over the configuration
    with a note when they differ. Returns (chirp, the configuration's profile, notes)."""
    profile = dataclasses.replace(DEFAULT_PROFILE, **fields)
    check_profile(profile, source or "the default chirp")
    from_config = profile_chirp(profile)
    # Which chirp quantities the configuration fixes: f0 needs the start frequency (with the
    # ADC start and slope it depends on), the others their own field.
    given = {
        "f0_hz": "start_freq_ghz" in fields,
        "slope_hz_per_s": "slope_mhz_per_us" in fields,
        "fs_hz": "sample_rate_ksps" in fields,
        "n_samples": "n_samples" in fields,
    }
    options = {"f0_hz": f0_hz, "slope_hz_per_s": slope_hz_per_s, "fs_hz": fs_hz, "n_samples": n_samples}
    notes: list[str] = []
    values = from_config.to_dict()
    for name, option in options.items():
        if option is None:
            continue
        have = values[name]
        if given[name] and float(option) != float(have):
            notes.append(f"{_OPTION_OF[name]} {option:g} overrides the capture configuration's {have:g} ({source})")
        values[name] = int(option) if name == "n_samples" else float(option)
    return Chirp(**values), profile, notes


def describe_chirp(chirp: Chirp) -> str:
    """One line for a chirp: first-sample frequency, slope, sample rate, samples."""
    return (
        f"first sample {chirp.f0_hz * 1e-9:.6g} GHz, slope {chirp.slope_hz_per_s * 1e-12:.6g} MHz/us, "
        f"{chirp.fs_hz * 1e-6:.6g} Msps, {chirp.n_samples} samples"
    )


def chirp_record(chirp: Chirp, profile: Profile | None, source) -> dict:
    """What ``<scan>.capture.json`` records of the chirp: the chirp used, and the configuration's
    profile and file when it had one (None: the chirp came from options and defaults)."""
    return {
        **chirp.to_dict(),
        "source": None if profile is None or source is None else str(source),
        "profile": None if profile is None else profile.to_dict(),
    }
