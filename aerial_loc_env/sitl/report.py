"""The flight report: SITL's dataflash log read on its own clock, the EKF's errors against the truth, the
touchdown, the summary figures, and the files ``aerial-loc sitl`` writes (never over a previous run's).
"""

from __future__ import annotations

import bisect
import csv
import json
import math
import os
from pathlib import Path

import numpy as np

from aerial_loc_env.errors import AerialLocError, ConfigError
from aerial_loc_env.world.maps.geo import distance_m, east_north_m

# what a run writes into its --out folder (track.png with matplotlib)
OUTPUT_FILES = ("errors.csv", "messages.txt", "summary.json", "track.png")


def signed_uint16(value: int) -> int:
    """A uint16 log field that holds a difference, read back as the signed 16-bit value it wrapped from."""
    return value - 0x10000 if value >= 0x8000 else value


def read_dataflash(path: str | os.PathLike, gps_instance: int = 0) -> dict[str, list]:
    """What SITL logged, on its own clock (TimeUS as seconds since boot): the truth (SIM), the EKF's position
    (POS), each as (t, lat, lon, alt AMSL), and the update intervals of GPS ``gps_instance`` (0 = GPS1) (t,
    GPA.Delta ms: the time between its last two updates as ArduPilot stamps them; over 0.245 s it marks the GPS
    unhealthy; the first is skipped: it has no update before it, ArduPilot logs the time since boot or a wrapped
    value there; the field is a uint16 of a difference of jitter-corrected stamps, so a stamp a few ms earlier
    than the one before reads 65536 - n: decoded as the signed n, never a 65 s gap), and EKF3's own horizontal
    position variance (t, XKV1.V07 + V08 of its first core, m^2: the north and east position states' variances)."""
    from pymavlink import DFReader

    log = DFReader.DFReader_binary(str(path), zero_time_base=True)
    out: dict[str, list] = {"truth": [], "ekf": [], "gps_delta_ms": [], "ekf_var_m2": [], "modes": [],
                            "messages": [], "gps_status": [], "ekf_status": []}
    first_gpa = True
    while (m := log.recv_match(type=["SIM", "POS", "GPA", "XKV1", "MODE", "MSG", "GPS", "XKF4"])) is not None:
        t, kind = m.TimeUS / 1e6, m.get_type()
        if kind == "MODE":
            out["modes"].append((t, int(m.ModeNum), int(m.Rsn)))
        elif kind == "MSG":
            out["messages"].append((t, str(m.Message)))
        elif kind == "GPS":
            if getattr(m, "I", 0) == gps_instance:
                out["gps_status"].append((t, int(m.Status)))
        elif kind == "XKF4":
            if m.C == 0:
                out["ekf_status"].append((t, int(m.SS)))
        elif kind == "XKV1":
            if m.C == 0:
                out["ekf_var_m2"].append((t, float(m.V07) + float(m.V08)))
        elif kind == "GPA":
            if getattr(m, "I", 0) == gps_instance:
                if first_gpa:
                    first_gpa = False
                else:
                    out["gps_delta_ms"].append((t, signed_uint16(int(m.Delta))))
        else:
            out["truth" if kind == "SIM" else "ekf"].append((t, float(m.Lat), float(m.Lng), float(m.Alt)))
    return out


#: ArduPilot's GPS health (AP_GPS::is_healthy): an update interval over this is a delayed frame, two in a row
#: make the GPS unhealthy, and so does a running average (0.98 old + 0.02 new, of intervals under 2 s) over
#: AVG_MAX_MS; an interval that runs backwards wraps (uint32) and counts as delayed
GPS_MAX_DELTA_MS = 245
GPS_AVG_MAX_MS = 215


def gps_unhealthy(deltas_ms: list[tuple[float, int]], since_s: float = -math.inf) -> list[tuple[float, str]]:
    """When ArduPilot's health rule for a GPS (``AP_GPS::is_healthy``'s timing part) fails on the logged update
    intervals (t, GPA.Delta ms, signed): (t, why) for each update at or after ``since_s`` at which it does. The
    running average runs over every interval from the first, as ArduPilot's does from boot (started at the window
    instead, its first interval alone would stand for the average)."""
    delayed, average, out = 0, 0.0, []
    for t, d in deltas_ms:
        delayed = delayed + 1 if (d > GPS_MAX_DELTA_MS or d < 0) else 0
        if 0 <= d < 2000:
            average = float(d) if average <= 0 else 0.98 * average + 0.02 * d
        if t < since_s:
            continue
        if delayed >= 2:
            out.append((t, f"{delayed} delayed updates in a row ({d} ms)"))
        elif average >= GPS_AVG_MAX_MS:
            out.append((t, f"average update interval {average:.0f} ms"))
    return out


def timed_horizontal_errors(truth: list, ekf: list, max_gap_s: float = 0.3) -> list[tuple[float, float]]:
    """(time, EKF minus truth in ground metres) for each EKF sample, the truth interpolated linearly at its time
    between the two samples around it (at most ``max_gap_s`` apart); samples outside the truth's span skipped."""
    times = [t[0] for t in truth]
    kept = []          # (time, EKF lat, lon, truth lat, lon)
    for t, lat, lon, _ in ekf:
        i = bisect.bisect_left(times, t)
        if i == 0 or i >= len(truth):
            if i < len(truth) and times[i] == t:
                tl, tn = truth[i][1], truth[i][2]
            else:
                continue
        else:
            (ta, la, na, _), (tb, lb, nb, _) = truth[i - 1], truth[i]
            if tb - ta > max_gap_s:
                continue
            w = (t - ta) / (tb - ta) if tb > ta else 0.0
            tl, tn = la + w * (lb - la), na + w * (nb - na)
        kept.append((t, lat, lon, tl, tn))
    if not kept:
        return []
    t, lat, lon, tl, tn = (np.asarray(c, dtype=np.float64) for c in zip(*kept, strict=True))
    return list(zip(t.tolist(), distance_m(tl, tn, lat, lon).tolist(), strict=True))


def horizontal_errors_m(truth: list, ekf: list) -> list[float]:
    """EKF minus truth, metres, the truth interpolated at each EKF sample's time (``timed_horizontal_errors``)."""
    return [e for _, e in timed_horizontal_errors(truth, ekf)]


def touchdown(truth: list, ekf: list, steps: list, land_at: tuple[float, float], t_landing: float | None,
              ekf_var_m2: list | None = None) -> dict:
    """Where and how the plane came down, on SITL's clock: the first truth sample of the landing sequence
    (from ``t_landing``) within 0.5 m of the ground height (the truth's median before take-off), the distance
    from there to the NAV_LAND point (along the final, south, and across it), the EKF's error at that moment and
    the horizontal accuracy it claimed on the dead reckoning before it (the largest sqrt of its north + east
    position variances, ``ekf_var_m2``: (t, m^2), from the last camera frame to touchdown: EKF3 shrinks them as
    it detects the landing, around touchdown), where the vehicle stopped; the last camera frame before it
    (altitude, seconds of dead reckoning)."""
    if not truth or t_landing is None:
        return {}
    ground = float(np.median([r[3] for r in truth[:50]]))
    down = next((r for r in truth if r[0] >= t_landing and r[3] <= ground + 0.5), None)
    if down is None:
        return {"landed": False}
    t_down = down[0]
    east, north = (float(v) for v in east_north_m(land_at[0], land_at[1], down[1], down[2]))
    at_down = [e for t, e in timed_horizontal_errors(truth, ekf) if abs(t - t_down) <= 0.5]
    rest = truth[-1]
    cam = [s for s in steps if s[1] == "camera" and s[0] <= t_down]
    t_fix = cam[-1][0] if cam else -math.inf
    var = [v for t, v in (ekf_var_m2 or []) if t_fix <= t <= t_down]
    return {"landed": True, "t_s": t_down, "distance_m": math.hypot(north, east),
            "along_m": -north, "cross_m": east,     # the final runs south: along = beyond the point, cross = east
            "ekf_error_m": float(at_down[len(at_down) // 2]) if at_down else math.nan,
            "ekf_sigma_m": math.sqrt(max(0.0, max(var))) if var else math.nan,
            "rest_from_land_point_m": float(distance_m(land_at[0], land_at[1], rest[1], rest[2])),
            "last_fix_alt_m": float(cam[-1][5]) if cam else math.nan,
            "dead_reckoning_s": t_down - cam[-1][0] if cam else math.nan}


#: the autopilot's messages that belong to a failsafe timeline
FAILSAFE_WORDS = ("ailsafe", "EKF variance", "Glitch", "stopped aiding", "is using", "source", "GPS", "Mission:",
                  "dead reckoning", "position")


#: EKF3's solution status bits (XKF4.SS, ArduPilot's nav_filter_status), in order from bit 0
EKF_STATUS_BITS = ("attitude", "horiz_vel", "vert_vel", "horiz_pos_rel", "horiz_pos_abs", "vert_pos", "terrain_alt",
                   "const_pos_mode", "pred_horiz_pos_rel", "pred_horiz_pos_abs", "takeoff_detected", "takeoff",
                   "touchdown", "using_gps", "gps_glitching", "gps_quality_good", "initialized",
                   "rejecting_airspeed", "dead_reckoning")


def ekf_status_change(before: int, after: int) -> str:
    """What changed between two EKF3 solution statuses, in words: '+dead_reckoning -horiz_pos_abs'."""
    words = [("+" if after >> i & 1 else "-") + name for i, name in enumerate(EKF_STATUS_BITS)
             if (before ^ after) >> i & 1]
    return " ".join(words)


def mode_name(vehicle: str, number: int) -> str:
    """ArduPilot's name of flight mode ``number`` for the vehicle (plane or copter)."""
    from pymavlink import mavutil

    table = mavutil.mode_mapping_apm if vehicle == "plane" else mavutil.mode_mapping_acm
    return table.get(int(number), str(number))


def failsafe_timeline(record: dict) -> dict:
    """What the autopilot did around a vision cut, on SITL's clock, seconds from the first fix withheld (the
    bridge's steps marked "cut"): its messages and mode changes (from its own log), its GPS fix type, when its
    EKF's solution changed, the fix back (the first camera fix sent after the cut), the reaction (the first mode
    change after the cut), the mission resumed (the first mode change or mission item after the fix came back),
    and the EKF's dead-reckoning drift (its error against the truth and the accuracy it claimed, sqrt of its
    north + east position variances) each second since the last fix."""
    steps = record.get("steps", [])
    cut = [st[0] for st in steps if st[1] == "cut"]
    if not cut:
        return {}
    t0 = cut[0]
    vehicle = record.get("vehicle", "copter")
    last_fix = max((st[0] for st in steps if st[1] == "camera" and st[0] < t0), default=t0)
    back = next((st[0] for st in steps if st[1] == "camera" and st[0] > cut[-1]), None)
    end = (back if back is not None else cut[-1]) + 60.0
    msgs = [(round(t - t0, 2), x) for t, x in record.get("log_messages", []) if t0 - 2.0 <= t <= end
            and any(w in x for w in FAILSAFE_WORDS + ("Vision",))]
    modes = [(round(t - t0, 2), mode_name(vehicle, n)) for t, n, _ in record.get("modes", []) if t0 <= t <= end]
    gps = record.get("gps_status", [])
    gps_lost = next((t for t, f in gps if t >= t0 and f < 3), None)
    gps_back = next((t for t, f in gps if back is not None and t >= back - 1.0 and f >= 3), None)
    ekf = [(round(t - t0, 2), ekf_status_change(prev, f)) for (t, f), (_, prev)
           in zip(record.get("ekf_status", [])[1:], record.get("ekf_status", []), strict=False)
           if t0 - 1.0 <= t <= end and f != prev]
    reaction = next((t for t, n, _ in record.get("modes", []) if t >= t0), None)
    resumed = None
    if back is not None:
        after = [t for t, _, _ in record.get("modes", []) if t >= back]
        items = [t for t, x in record.get("log_messages", []) if t >= back and x.startswith("Mission: ")]
        resumed = min(after + items, default=None)
    var = record.get("ekf_var_m2", [])
    var_t = [t for t, _ in var]
    drift = []
    errors = [(t, e) for t, e in record.get("timed_errors", []) if last_fix <= t <= (back or cut[-1]) + 1.0]
    for k in range(int((back or cut[-1]) - last_fix) + 2):
        near = [e for t, e in errors if abs(t - (last_fix + k)) <= 0.25]
        if near:
            i = max(0, bisect.bisect_right(var_t, last_fix + k) - 1)
            sigma = math.sqrt(max(0.0, var[i][1])) if var else math.nan
            drift.append((k, round(float(np.median(near)), 2), round(sigma, 2)))
    return {"cut_s": (cut[-1] - t0) if back is None else back - t0, "last_fix_before_s": round(last_fix - t0, 2),
            "gps_no_fix_s": None if gps_lost is None else round(gps_lost - t0, 2),
            "reaction_s": None if reaction is None else round(reaction - t0, 2),
            "fix_back_s": None if back is None else round(back - t0, 2),
            "gps_fix_back_s": None if gps_back is None else round(gps_back - t0, 2),
            "resumed_s": None if resumed is None else round(resumed - t0, 2),
            "modes": modes, "messages": msgs, "ekf_status_changes": ekf,
            "drift_m": drift, "drift_max_m": max((d[1] for d in drift), default=math.nan)}


def vision_fix_s(steps: list, after: float | None = None) -> float:
    """Seconds the bridge sent camera fixes (sum of step intervals, each at most 1 s, ending on a camera step)."""
    total = 0.0
    for a, b in zip(steps, steps[1:], strict=False):
        t0, t1, src = a[0], b[0], b[1]
        if src == "camera" and (after is None or t0 >= after):
            total += min(1.0, t1 - t0)
    return total


def summary(record: dict) -> dict:
    """The figures the issue asks for, from a mission record."""
    e = np.asarray(record["horizontal_errors_m"], dtype=float)
    g = np.asarray(record["gps_gaps_ms"], dtype=float)
    legs = np.asarray(record["leg_errors_m"], dtype=float)
    steps = record.get("steps", [])
    est = np.asarray([s[2] for s in steps if s[1] == "camera" and s[2] is not None], dtype=float)
    frames = [s[0] for s in steps if s[1] == "camera"]
    # between consecutive camera frames (not across the camera out of range: pad or lost steps between)
    dt = np.asarray([b[0] - a[0] for a, b in zip(steps, steps[1:], strict=False)
                     if a[1] == "camera" and b[1] == "camera"], dtype=float)
    frame_intervals = ({"median": float(np.median(dt)), "p95": float(np.percentile(dt, 95)), "max": float(dt.max())}
                       if dt.size else {})
    events = [x for _, x in record["texts"] if any(k in x for k in ("ailsafe", "EKF variance", "Glitch",
                                                                     "stopped aiding", "is using", "source"))]
    out = {"mission": record.get("mission", "gps-input"),
           "vehicle": record.get("vehicle", "copter"), "wind": record.get("wind"),
           # copter: the last waypoint reached (then RTL landed: the run waits for the disarm); plane: touched down
           "mission_completed": (record.get("touchdown", {}).get("landed", False) if record.get("vehicle") == "plane"
                                 else record.get("last_wp", 3) in record["reached"]),
           "legs_ekf_rmse_m": float(np.sqrt(np.mean(legs ** 2))) if legs.size else math.nan,
           "legs_ekf_max_m": float(legs.max()) if legs.size else math.nan,
           "ekf_rmse_m": float(np.sqrt(np.mean(e ** 2))) if e.size else math.nan,
           "ekf_max_m": float(e.max()) if e.size else math.nan,
           "estimator_rmse_m": float(np.sqrt(np.mean(est ** 2))) if est.size else math.nan,
           "estimator_max_m": float(est.max()) if est.size else math.nan,
           # in SITL's seconds (the record's times are on SITL's clock)
           "vision_fix_s": vision_fix_s(steps, record.get("t_denied")),
           "fix_to_arm_s": record["fix_to_arm_s"], "flight_s": record["flight_s"],
           "speedup": record.get("speedup", 1.0), "speedup_achieved": record.get("speedup_achieved", math.nan),
           # how the agent kept up: camera frames and the intervals between them, SITL seconds
           "camera_frames": len(frames), "frame_interval_s": frame_intervals,
           "share_of_flight_with_absolute_position": (sum(1 for _, f in record["ekf_flags"] if f & 16)
                                                      / max(1, len(record["ekf_flags"]))),
           "ekf_flags_seen": sorted({f for _, f in record["ekf_flags"]}),
           "gps_gaps_over_245ms": int((g > 245).sum()), "gps_gap_max_ms": float(g.max()) if g.size else math.nan,
           "gps_gap_max_before_fix_ms": float(record.get("gps_gap_max_before_fix_ms", math.nan)),
           "events": list(dict.fromkeys(events))}
    deltas = record.get("gps_deltas_ms", [])
    if deltas:     # ArduPilot's own health rule on its GPS update intervals (capture-stamped fixes: resends
        #            carry the frame's stamp, so the intervals are 0 between resends and a frame's between frames)
        since = float(record.get("gps_deltas_since_s", deltas[0][0]))
        bad = gps_unhealthy(deltas, since)
        out["gps_unhealthy"] = len(bad)
        out["gps_unhealthy_first"] = [(round(t - since, 2), why) for t, why in bad[:5]]
        positive = [d for t, d in deltas if d > 0 and t >= since]
        out["gps_fix_interval_ms"] = {"median": float(np.median(positive)), "max": float(max(positive))} \
            if positive else {}
    lat = np.asarray(record.get("fix_latency_s", []), dtype=float)
    if lat.size:
        out["fix_latency_ms"] = {"min": float(lat.min() * 1e3), "median": float(np.median(lat) * 1e3),
                                 "p95": float(np.percentile(lat, 95) * 1e3)}
    if record.get("external_position"):
        out["external_position"] = record["external_position"]
    if record.get("vision_cut"):
        out["vision_cut"] = {"at": record["vision_cut"][0], "seconds": record["vision_cut"][1],
                             **failsafe_timeline(record)}
    if record.get("acquisition_errors_m"):
        out["acquisition_ekf_max_m"] = float(max(record["acquisition_errors_m"]))
    if record.get("touchdown"):
        out["touchdown"] = record["touchdown"]
    if record.get("t_denied") is not None:     # the EKF after the GNSS was switched off
        t_d = record["t_denied"]
        after = [r for r in record["truth"] if r[0] >= t_d], [r for r in record["ekf"] if r[0] >= t_d]
        d = np.asarray(horizontal_errors_m(*after), dtype=float)
        out["denied_ekf_rmse_m"] = float(np.sqrt(np.mean(d ** 2))) if d.size else math.nan
        out["denied_ekf_max_m"] = float(d.max()) if d.size else math.nan
    return out


def _free_sibling(out_dir: Path) -> Path:
    """The first of ``<out>-2``, ``<out>-3``, ... that does not exist (offered when ``out`` is taken)."""
    k = 2
    while out_dir.with_name(f"{out_dir.name}-{k}").exists():
        k += 1
    return out_dir.with_name(f"{out_dir.name}-{k}")


def check_out_dir(out_dir: Path) -> None:
    """Refuse, before the flight, an ``--out`` the report could not be written to or would overwrite: a file,
    a folder under a file, a folder this user cannot write, or one that holds a previous run's results."""
    out_dir = Path(out_dir)
    what = "errors.csv, messages.txt, summary.json, track.png"
    if out_dir.exists() and not out_dir.is_dir():
        raise ConfigError(f"--out {out_dir}: is a file, not a folder; give a folder for the run's {what} "
                          f"(e.g. --out {_free_sibling(out_dir)})")
    if out_dir.is_dir():
        taken = [name for name in OUTPUT_FILES if os.path.lexists(out_dir / name)]
        if taken:
            raise ConfigError(f"--out {out_dir}: holds a previous run's {', '.join(taken)}; a run never overwrites "
                              f"results: give a new folder (e.g. --out {_free_sibling(out_dir)}) or move those away")
        folder = out_dir
    else:
        folder = next(p for p in out_dir.absolute().parents if p.exists())
        if not folder.is_dir():
            raise ConfigError(f"--out {out_dir}: {folder} is a file, so the folder cannot be made there; give a "
                              "folder path")
    if not os.access(folder, os.W_OK | os.X_OK):
        raise ConfigError(f"--out {out_dir}: {folder} is not writable by this user; give a folder you may write")


def write_outputs(record: dict, out_dir: Path) -> list[Path]:
    """errors.csv (time, EKF, error), messages.txt (STATUSTEXT), summary.json and, with matplotlib, track.png
    (true and EKF tracks, estimates; errors over time). None of them may exist already (``check_out_dir``)."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)

    def create(name: str, binary: bool = False):
        try:
            return open(out_dir / name, "xb") if binary else open(out_dir / name, "x", newline="")
        except FileExistsError as exc:
            raise AerialLocError(f"--out {out_dir}: {name} appeared there during the flight; it is left as it is "
                                 "(a run never overwrites results)") from exc

    paths = [out_dir / "errors.csv", out_dir / "messages.txt", out_dir / "summary.json"]
    with create("summary.json") as f:
        f.write(json.dumps(summary(record), indent=1) + "\n")
    truth, ekf = record["truth"], record["ekf"]
    t0 = truth[0][0] if truth else 0.0
    lines = [f"{t - t0:8.1f} s  {x}" for t, x in record["texts"]]
    if record.get("t_denied") is not None:
        lines.append(f"{record['t_denied'] - t0:8.1f} s  [{record.get('denial', 'SIM_GPS1_ENABLE 0')}]")
    with create("messages.txt") as f:
        f.write("\n".join(sorted(lines, key=lambda x: float(x.split()[0]))) + "\n")
    with create("errors.csv") as f:
        w = csv.writer(f)
        w.writerow(["t_s", "ekf_lat_deg", "ekf_lon_deg", "ekf_alt_m", "horizontal_error_m"])
        err_at = dict(record.get("timed_errors", []))
        for t, lat, lon, alt in ekf:
            if t in err_at:
                w.writerow([f"{t - t0:.2f}", f"{lat:.8f}", f"{lon:.8f}", f"{alt:.2f}", f"{err_at[t]:.3f}"])
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        return paths
    if truth:
        lat0, lon0 = truth[0][1], truth[0][2]

        def en(rows):
            east, north = east_north_m(lat0, lon0, [r[1] for r in rows], [r[2] for r in rows])
            return east.tolist(), north.tolist()

        fig, (ax, ax2) = plt.subplots(1, 2, figsize=(10, 3.6), gridspec_kw={"width_ratios": [1.4, 1]})
        ax.plot(*en(truth), "g-", lw=2, label="SITL truth")
        ax.plot(*en(ekf), "r--", lw=1.2, label="EKF")
        if record.get("estimates"):
            ax.plot(*en(record["estimates"]), "b.", ms=2, label="estimates (camera)")
        ax.set_xlabel("east of take-off, m")
        ax.set_ylabel("north, m")
        wind = record.get("wind")
        blows = "" if not wind else f", wind {wind[0]:g} m/s from {wind[1]:g} deg" + (
            f" gusting {wind[2]:g}" if len(wind) > 2 and wind[2] else "")
        ax.set_title(f"{record.get('vehicle', 'copter')}, {record.get('mission', 'gps-input')}{blows}: track",
                     fontsize=9)
        ax.legend(fontsize=7)
        timed = record.get("timed_errors", [])
        ax2.plot([t - t0 for t, _ in timed], [e for _, e in timed], "r-", lw=1, label="EKF vs truth")
        cam = [s for s in record.get("steps", []) if s[1] == "camera" and s[2] is not None]
        if cam:
            ax2.plot([s[0] - t0 for s in cam], [s[2] for s in cam], "b.", ms=2, label="estimator vs truth")
        if record.get("t_denied") is not None:
            ax2.axvline(record["t_denied"] - t0, color="k", lw=0.8, ls=":", label="GNSS off")
        cut = [st[0] for st in record.get("steps", []) if st[1] == "cut"]
        if cut:                         # the vision cut: the fix withheld from the autopilot
            ax2.axvspan(cut[0] - t0, cut[-1] - t0, color="orange", alpha=0.25, label="vision cut")
            ax.plot(*en([r for r in truth if cut[0] <= r[0] <= cut[-1]]), "-", color="orange", lw=2.5,
                    label="truth during the cut")
        ax2.set_yscale("log")
        ax2.set_xlabel("time since arming, s")
        ax2.set_ylabel("horizontal error, m")
        ax2.legend(fontsize=7)
        with create("track.png", binary=True) as f:
            fig.savefig(f, format="png", dpi=90, bbox_inches="tight")
        plt.close(fig)
        paths.append(out_dir / "track.png")
    return paths
