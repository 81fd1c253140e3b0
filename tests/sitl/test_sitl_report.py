"""The flight report: the EKF's errors against the interpolated truth in ground metres, the touchdown, the time
on the vision fix, and the output folder: checked before the flight, never written over."""

from __future__ import annotations

import json
import math

import pytest

from aerial_loc_env.errors import AerialLocError, ConfigError
from aerial_loc_env.sitl.report import (
    OUTPUT_FILES,
    check_out_dir,
    signed_uint16,
    summary,
    timed_horizontal_errors,
    touchdown,
    vision_fix_s,
    write_outputs,
)
from aerial_loc_env.world.maps.geo import offset_latlon


def _at(lat0: float, lon0: float, east_m: float, north_m: float) -> tuple[float, float]:
    lat, lon = offset_latlon(lat0, lon0, east_m, north_m)
    return float(lat), float(lon)


def test_touchdown_is_the_first_ground_contact_of_the_landing():
    """Truth descending south onto a point (ground 30 m AMSL), touching 20 m short of it and rolling on: the
    touchdown is the first sample within 0.5 m of the ground after the landing began (not a bounce or the taxi
    before take-off), measured in ground metres along the final (south) and across it; the EKF's error there and
    the accuracy it claimed on the dead reckoning (its largest from the last camera frame to touchdown); the last
    camera frame's altitude and the dead reckoning after it."""
    lat0, lon0 = -35.0, 149.0
    # on the ground before take-off (t < 10), then the final from 100 m north at 40 m to touchdown 21 m short,
    # 3 m east of the line; the EKF 2 m north of the truth
    truth = [(0.1 * k, lat0, lon0, 30.0) for k in range(100)]
    truth += [(10.0 + 0.1 * k, *_at(lat0, lon0, 3.0, 100.0 - k), 30.0 + max(0.0, 40.0 - 0.5 * k)) for k in range(90)]
    ekf = [(t, *_at(la, lo, 0.0, 2.0), a) for t, la, lo, a in truth]
    steps = [(12.0, "camera", 1.0, 0.0, 0.0, 39.0), (14.0, "camera", 1.0, 0.0, 0.0, 30.5),
             (15.0, "lost", None, 0, 0, 28.0)]
    # the EKF's own: 0.5 m at the last fix, growing to 5 m on the dead reckoning, shrunk as it detects the landing
    var = [(0.0, 1.0), (13.9, 0.25), (16.5, 16.0 + 9.0), (17.5, 0.64), (18.5, 400.0)]
    td = touchdown(truth, ekf, steps, (lat0, lon0), t_landing=10.0, ekf_var_m2=var)
    assert td["landed"] and td["t_s"] == pytest.approx(10.0 + 0.1 * 79)      # 40 - 0.5 k <= 0.5 first at k = 79
    assert td["ekf_sigma_m"] == pytest.approx(5.0)
    assert td["along_m"] == pytest.approx(-(100 - 79), abs=1e-6) and td["cross_m"] == pytest.approx(3.0, abs=1e-6)
    assert td["distance_m"] == pytest.approx(math.hypot(21.0, 3.0), abs=1e-6)
    assert td["rest_from_land_point_m"] == pytest.approx(math.hypot(11.0, 3.0), abs=1e-6)    # k = 89: 11 m north
    assert td["ekf_error_m"] == pytest.approx(2.0, abs=1e-6) and td["last_fix_alt_m"] == 30.5
    assert td["dead_reckoning_s"] == pytest.approx(td["t_s"] - 14.0)
    assert touchdown(truth[:120], ekf, steps, (lat0, lon0), t_landing=10.0) == {"landed": False}
    assert touchdown(truth, ekf, steps, (lat0, lon0), t_landing=None) == {}


def test_errors_interpolate_the_truth_and_vision_time_counts_camera_steps():
    """Truth moving east at 10 m/s sampled at 10 Hz: an EKF sample half-way between two truth samples at the
    interpolated position has no error (nearest-sample matching would say 0.5 m), one 3 m north of it 3 ground
    metres; samples outside the truth's span are skipped."""
    truth = [(0.1 * k, *_at(-35.0, 149.0, float(k), 0.0), 50.0) for k in range(10)]
    ekf = [(0.45, *_at(-35.0, 149.0, 4.5, 0.0), 50.0), (0.55, *_at(-35.0, 149.0, 5.5, 3.0), 50.0),
           (5.0, -35.0, 149.0, 50.0)]
    (t, e), (t2, e2) = timed_horizontal_errors(truth, ekf)
    assert (t, t2) == (0.45, 0.55) and e < 1e-6 and e2 == pytest.approx(3.0, abs=1e-6)
    assert timed_horizontal_errors(truth, []) == []
    steps = [(0.0, "pad", 1, 0, 0), (0.5, "camera", 1, 0, 0), (0.75, "camera", 1, 0, 0), (5.0, "camera", 1, 0, 0),
             (5.25, "lost", 1, 0, 0)]
    assert vision_fix_s(steps) == pytest.approx(0.5 + 0.25 + 1.0)    # a 4.25 s hole counts 1 s at most
    assert vision_fix_s(steps, after=0.6) == pytest.approx(1.0)      # only intervals that start after


def test_out_folder_is_checked_before_the_flight(tmp_path):
    """Where the report could not go, or would overwrite a previous run's, the flight does not start: an
    existing file, a folder under a file, a folder holding any of the run's files (a free name is offered)."""
    check_out_dir(tmp_path / "new" / "run")         # made when written
    (tmp_path / "empty").mkdir()
    check_out_dir(tmp_path / "empty")               # nothing there to overwrite
    (tmp_path / "notes.txt").write_text("mine")
    with pytest.raises(ConfigError, match=r"--out .*notes.txt: is a file, not a folder; .*--out .*notes.txt-2"):
        check_out_dir(tmp_path / "notes.txt")
    with pytest.raises(ConfigError, match="notes.txt is a file, so the folder cannot be made there"):
        check_out_dir(tmp_path / "notes.txt" / "run")
    for name in OUTPUT_FILES:
        prev = tmp_path / f"prev_{name}"
        prev.mkdir()
        (prev / name).write_text("a previous run")
        (tmp_path / f"prev_{name}-2").mkdir()       # taken too: the next free name is offered
        with pytest.raises(ConfigError, match=rf"holds a previous run's {name}; a run never overwrites results: "
                                              rf"give a new folder \(e.g. --out .*prev_{name}-3\)"):
            check_out_dir(prev)
        assert (prev / name).read_text() == "a previous run"


def _record() -> dict:
    truth = [(100.0 + 0.1 * k, *_at(-35.0, 149.0, float(k), 0.0), 80.0) for k in range(20)]
    ekf = [(100.05 + 0.1 * k, *_at(-35.0, 149.0, k + 0.5, 1.0), 80.0) for k in range(19)]
    timed = timed_horizontal_errors(truth, ekf)
    steps = [(100.0 + 0.25 * k, "camera", 1.5, float(k), 0.0, 80.0) for k in range(8)]
    return {"vehicle": "copter", "mission": "gps-input", "truth": truth, "ekf": ekf, "timed_errors": timed,
            "horizontal_errors_m": [e for _, e in timed], "leg_errors_m": [e for _, e in timed],
            "texts": [(100.0, "EKF3 IMU0 is using GPS"), (101.0, "Mission: 1 Takeoff")], "ekf_flags": [(100.0, 16)],
            "gps_gaps_ms": [100.0, 110.0], "reached": [1, 2, 3], "last_wp": 3, "steps": steps,
            "fix_to_arm_s": 3.0, "flight_s": 2.0, "t_denied": None, "estimates": [(100.0, -35.0, 149.0)]}


def test_report_writes_its_files_and_never_over_a_previous_run(tmp_path):
    record = _record()
    paths = write_outputs(record, tmp_path / "run")
    assert {p.name for p in paths} >= set(OUTPUT_FILES) - {"track.png"}
    s = json.loads((tmp_path / "run" / "summary.json").read_text())
    assert s == json.loads(json.dumps(summary(record))) and s["ekf_max_m"] == pytest.approx(1.0, abs=1e-6)
    rows = (tmp_path / "run" / "errors.csv").read_text().splitlines()
    assert rows[0].startswith("t_s,") and len(rows) == 1 + len(record["timed_errors"])
    before = {p.name: p.read_bytes() for p in paths}
    with pytest.raises(AerialLocError, match="summary.json appeared there during the flight; it is left as it is"):
        write_outputs(record, tmp_path / "run")
    assert {p.name: p.read_bytes() for p in paths} == before


def test_gps_update_interval_decoded_as_signed():
    """GPA.Delta is a uint16 of a stamp difference: a stamp 12 ms earlier than the one before is logged as 65524
    and must read as -12 (no gap), while real gaps and ordinary intervals keep their values."""
    assert signed_uint16(65524) == -12
    assert signed_uint16(0xFFFF) == -1
    assert signed_uint16(100) == 100 and signed_uint16(245) == 245 and signed_uint16(0x7FFF) == 0x7FFF
