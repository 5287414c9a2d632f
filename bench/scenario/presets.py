"""Named presets (faults, stress cases, hazardous terrain): real incidents and stress cases, each a scenario layer (``--preset NAME``).

A preset is a partial scenario table laid over the scenario file and under
``--set`` overrides: its tables merge into the file's, and its ``faults`` are
appended to the file's. Each has one line of provenance (``landbench faults
list``). The values are scaled to this bench's lander and its 500 m hand-over;
the README's *Faults* section gives the reasoning for each.

Presets that change a dispersed field (``sun_5deg``) pin its dispersion to the
preset's value (``uniform`` with ``low = high``: one draw as before, so every
other path draws exactly as without the preset).
"""

from __future__ import annotations

import copy
from dataclasses import dataclass
from typing import Any


@dataclass(frozen=True)
class Preset:
    """One named layer: its provenance line and the scenario table it lays over."""

    name: str
    provenance: str
    layer: dict[str, Any]


PRESETS: dict[str, Preset] = {p.name: p for p in (
    Preset("im1", "IM-1 Odysseus (Feb 2024): laser altimeters inhibited (safety switch not armed), the backup's "
                  "ranges flagged invalid for the whole descent; it landed tipped over at about twice the planned "
                  "lateral speed. Here: altimeter flagged_invalid from hand-over to touchdown",
           {"faults": [{"kind": "flagged_invalid", "target": "altimeter"}]}),
    Preset("im2", "IM-2 Athena (Mar 2025): altimeter noisy all the way down, landed on its side in a crater. "
                  "Here: altimeter noise x8 from hand-over",
           {"faults": [{"kind": "noise", "target": "altimeter", "factor": 8.0}]}),
    Preset("beresheet", "Beresheet (Apr 2019): an IMU fault, then a computer reset that cut the main engine; it "
                        "crashed. Here: gyro output lost (dropout) for 2 s at 150 m, then a reset at 120 m "
                        "with the engine off for 3 s",
           {"faults": [{"kind": "dropout", "target": "imu.gyro", "altitude_m": 150.0, "duration_s": 2.0},
                       {"kind": "computer_reset", "altitude_m": 120.0, "down_s": 3.0}]}),
    Preset("hakuto_r", "Hakuto-R M1 (Apr 2023): a 3 km altimeter jump at a crater rim was rejected as a sensor "
                       "failure and the lander ran out of fuel believing it was on the ground. Here: a 150 m "
                       "plateau under the start of the track that the onboard terrain model lacks",
           {"faults": [{"kind": "terrain_step", "height_m": 150.0, "center_xy_m": [-130.0, 90.0],
                        "radius_m": 60.0}]}),
    Preset("dead_altimeter", "IM-1's situation without its flagged-but-good backup ranges: no altimeter range at "
                             "all for the whole descent (the issue's first try, sensors.altimeter.dropout_prob = 1). "
                             "Here: altimeter dropout from hand-over to touchdown",
           {"faults": [{"kind": "dropout", "target": "altimeter"}]}),
    Preset("slim", "SLIM (Jan 2024): lost part of one of its two main-engine nozzles at about 50 m: thrust loss "
                   "plus an off-axis torque; it landed on its nose. Here: 35 % thrust loss and 60 N m about body y "
                   "from 50 m",
           {"faults": [{"kind": "thrust_loss", "fraction": 0.35, "torque_B_Nm": [0.0, 60.0, 0.0],
                        "altitude_m": 50.0}]}),
    Preset("schiaparelli", "Schiaparelli (Oct 2016): the IMU's rate saturated for about 1 s, the integrated "
                           "attitude went wrong and the altitude estimate negative; it released its parachute "
                           "and fell. Here: the gyro reads its full scale (a 0.35 rad/s step on x) for 1 s at 100 m",
           {"faults": [{"kind": "bias_step", "target": "imu.gyro", "axes": [0], "value": 0.35,
                        "altitude_m": 100.0, "duration_s": 1.0}]}),
    Preset("camera_blackout_5s", "Stress: no camera frame for 5 s from t = 10 s (around 340 m)",
           {"faults": [{"kind": "camera_blackout", "t_s": 10.0, "duration_s": 5.0}]}),
    Preset("frame_drop_50", "Stress: every camera frame lost with probability 0.5 for the whole descent",
           {"faults": [{"kind": "frame_drop", "probability": 0.5}]}),
    Preset("sun_5deg", "Stress: the sun 5 deg above the horizon (long shadows; the issue's low-sun case)",
           {"sun": {"elevation_deg": 5.0},
            "dispersions": {"sun.elevation_deg": {"dist": "uniform", "low": 5.0, "high": 5.0}}}),
    Preset("featureless_mare", "Stress: a smooth mare with 1 % of the equilibrium crater density, no boulders, "
                               "2 % albedo contrast and 0.5 m roughness (few trackable features)",
           {"terrain": {"crater_density_per_km2": 200.0, "boulder_density_per_km2": 0.0,
                        "albedo_contrast": 0.02, "roughness_rms_m": 0.5}}),
)}
# Scenario presets that are not part of the fault matrix (``landbench faults --presets all``).
TERRAIN_PRESETS: dict[str, Preset] = {p.name: p for p in (
    Preset("hazardous", "Issue 14: hazardous terrain at the target: no cleared landing ellipse, a smooth site "
                        "chosen from orbit (craters at 10 % of the equilibrium density) strewn with boulders "
                        "(25 000 per km^2 of D >= 0.5 m, 50 x the default), so that a blind landing is unsafe "
                        "about 30 % of the time; touchdown footprints scored against the fine truth DEM",
           {"terrain": {"target_clear_radius_m": 0.0, "crater_density_per_km2": 2000.0,
                        "boulder_density_per_km2": 25000.0},
            "hazard": {"scoring": "on"}}),
)}
REFERENCE = Preset("nominal", "Reference: no fault (the false-alarm rate of the flight software's monitoring)", {})


def preset_names() -> list[str]:
    """The presets of ``landbench faults --presets all``, in order (the reference ``nominal`` is not one)."""
    return list(PRESETS)


def get_preset(name: str) -> Preset:
    """A preset by name (``nominal``: the reference, no fault).

    Raises:
        ValueError: One line naming the unknown preset and the known ones.
    """
    if name == REFERENCE.name:
        return REFERENCE
    if name in TERRAIN_PRESETS:
        return TERRAIN_PRESETS[name]
    try:
        return PRESETS[name]
    except KeyError:
        raise ValueError(f"--preset {name!r}: no such preset; allowed: "
                         f"{', '.join([*PRESETS, REFERENCE.name, *TERRAIN_PRESETS])} (landbench faults list)") from None


def apply_preset(data: dict[str, Any], name: str) -> dict[str, Any]:
    """Lay preset ``name`` over a raw scenario table: tables merge, ``faults`` are appended. Returns a new table."""
    out = copy.deepcopy(data)
    _merge(out, copy.deepcopy(get_preset(name).layer))
    return out


def _merge(base: dict[str, Any], layer: dict[str, Any]) -> None:
    for k, v in layer.items():
        if k == "faults":
            base[k] = [*(base.get(k) or []), *v]
        elif isinstance(v, dict) and isinstance(base.get(k), dict):
            _merge(base[k], v)
        else:
            base[k] = v
