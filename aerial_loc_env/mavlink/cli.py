"""``aerial-loc mavlink``: fly a scenario with an agent in real time and stream its estimates to an autopilot.

The simulation and the sender run at their own rates: each env step publishes a fix into the sender's slot and
the sender thread emits at ``--rate-hz`` whatever the latest fix is. ``--speed`` scales simulated time
(1 = real time, 4 = four times faster, 0 = each frame's fix once per sender tick, e.g. replay into a
logger). ``--demo`` streams a synthetic circular track without the env (to test a SITL setup). ``--follow``
makes the simulated camera follow the simulator's true vehicle (SITL's SIM_STATE, never the EKF's
GLOBAL_POSITION_INT), closing the loop.
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import sys
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from typing import Any

import numpy as np

from aerial_loc_env.config import build_config, parse_assignments
from aerial_loc_env.errors import AerialLocError, ConfigError
from aerial_loc_env.mavlink.bridge import EstimateBridge
from aerial_loc_env.mavlink.fix import FixPolicy
from aerial_loc_env.mavlink.messages import MESSAGE_KINDS, ODOMETRY_FRAMES
from aerial_loc_env.mavlink.sender import MavlinkSender, SenderConfig, SenderStats, VehicleState
from aerial_loc_env.world.maps.geo import east_north_m, offset_latlon

ALIASES = {"gps": "gps_input", "gps_input": "gps_input", "vision": "vision_position_estimate",
           "vision_position_estimate": "vision_position_estimate", "odom": "odometry", "odometry": "odometry",
           "external_position": "external_position", "extpos": "external_position"}
SITL_HOME = "-35.363261,149.165230,584.0"   # ArduPilot SITL's default home (CMAC)
# 0.5 m per axis at 4 Hz: the reported accuracies (h 0.7 m, speed 0.8 m/s, hdop 0.5) pass ArduPilot's default
# GPS checks (5 m, 1 m/s, GPS_HDOP_GOOD 1.4); 2 m reported 3.2 m/s speed accuracy and was never used
DEMO_NOISE_M = 0.5
# the terrain heights a map may declare, m AMSL (the Dead Sea shore to above the highest airfields)
GROUND_AMSL_RANGE_M = (-500.0, 9000.0)
# the simulator's speedups the bridge follows: its send rate and the camera's frames scale with it
SIM_SPEEDUP_RANGE = (0.1, 20.0)


def build_parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(prog="aerial-loc mavlink", description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    src = ap.add_argument_group("what to fly")
    src.add_argument("--scenario", help="registered env id, e.g. AerialLoc/...  (aerial-loc scenarios)")
    src.add_argument("--agent", help="agent spec name (aerial-loc agents)")
    src.add_argument("--demo", action="store_true", help="synthetic circular track, no env or agent needed")
    src.add_argument("--origin", default=SITL_HOME, help="--demo: LAT,LON,ALT_AMSL of the track centre")
    src.add_argument("--seed", type=int, default=0)
    src.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                     help="a scenario override (JSON value; repeatable), e.g. flight.rate_hz=5")
    src.add_argument("--speed", type=float, default=1.0,
                     help="simulated seconds per real second; 0 = as fast as the sender takes each frame's "
                          "fix (one per --rate-hz tick)")
    src.add_argument("--duration-s", type=float, default=0.0,
                     help="stop after N real seconds; 0: at the end")
    src.add_argument("--loop", action="store_true", help="restart the episode when it ends")
    src.add_argument("--follow", action="store_true", help="the camera follows the autopilot's vehicle")
    src.add_argument("--pad-radius-m", type=float, default=math.inf,
                     help="--follow: the take-off pad fix holds while the vehicle is within this distance of the "
                          "pad; beyond it, until the camera is in range, no fix (a fixed wing's take-off run)")
    src.add_argument("--sim-speedup", type=float, default=1.0,
                     help="--follow: the simulator runs this many times faster than real time (SITL --speedup); "
                          "the camera's frame times and the odometry follow the simulator's clock")
    src.add_argument("--ground-amsl-m", type=float, default=None,
                     help="terrain height of the map, m AMSL (default: the map's own, if it declares one)")
    link = ap.add_argument_group("MAVLink")
    link.add_argument("--connect", default="udpout:127.0.0.1:14550",
                      help="pymavlink connection string: udpout:H:P, udpin:H:P, tcp:H:P, tcpin:H:P, "
                           "/dev/ttyACM0,BAUD")
    link.add_argument("--message", action="append", default=None,
                      help=f"message(s) to send, repeatable or comma-separated: {', '.join(MESSAGE_KINDS)} "
                           "(aliases gps, vision, odom, extpos: MAV_CMD_EXTERNAL_POSITION_ESTIMATE at "
                           "--external-position-hz, for an autopilot dead reckoning); default gps_input")
    link.add_argument("--external-position-hz", type=float, default=1.0,
                      help="rate of the external_position message (low-rate global fixes)")
    link.add_argument("--rate-hz", type=float, default=10.0)
    link.add_argument("--sysid", type=int, default=1)
    link.add_argument("--compid", type=int, default=197)
    link.add_argument("--gps-id", type=int, default=0, help="GPS_INPUT.gps_id (the GPS instance)")
    link.add_argument("--gps-yaw", action="store_true", help="fill GPS_INPUT.yaw from the estimate")
    link.add_argument("--odometry-frames", default="local_frd", choices=tuple(ODOMETRY_FRAMES))
    link.add_argument("--signing-key", default="", help="MAVLink 2 signing: 64 hex digits or a passphrase")
    link.add_argument("--signing-link-id", type=int, default=0)
    link.add_argument("--baud", type=int, default=57600)
    ap.add_argument("--quiet", action="store_true", help="no live status line")
    return ap


def _messages(values: list[str] | None) -> tuple[str, ...]:
    out: list[str] = []
    for value in values or ["gps_input"]:
        for name in filter(None, (v.strip().lower() for v in value.split(","))):
            if name not in ALIASES:
                raise ConfigError(f"--message {name!r}: unknown; use {', '.join(MESSAGE_KINDS)} "
                                  "(or gps, vision, odom, extpos)")
            if ALIASES[name] not in out:
                out.append(ALIASES[name])
    return tuple(out)


def sender_config(args: argparse.Namespace) -> SenderConfig:
    return build_config(SenderConfig, {
        "connect": args.connect, "messages": _messages(args.message), "rate_hz": args.rate_hz,
        "system_id": args.sysid, "component_id": args.compid, "gps_id": args.gps_id, "gps_yaw": args.gps_yaw,
        "odometry_frames": args.odometry_frames, "signing_key": args.signing_key,
        "signing_link_id": args.signing_link_id, "baud": args.baud,
        "request_vehicle_hz": 20.0 if args.follow else 0.0, "sim_speedup": args.sim_speedup,
        "external_position_hz": args.external_position_hz,
    }, where="aerial-loc mavlink options")


@dataclass(frozen=True)
class Step:
    """One simulation step as the bridge needs it."""

    time_s: float
    estimate: Any
    altitude_m: float
    yaw_fallback_rad: float | None
    error_m: float | None = None     # the simulator's position error, for the status line only
    source: str = "camera"           # follow mode: "pad" (take-off point), "camera" (a frame), "lost"


@dataclass(frozen=True)
class _Estimate:
    x_m: float
    y_m: float
    yaw_rad: float | None
    cov_xy_m2: np.ndarray
    status: str = "ok"


class DemoTrack:
    """A circle flown at constant speed about a geographic centre, with Gaussian estimate noise.

    World metres are east and north on the WGS84 tangent plane at the centre (``world.maps.geo``, as a synthetic
    map's ``LocalTangentGeoref``): the circle's radius is ground metres.
    """

    def __init__(self, origin: str, seed: int, radius_m: float = 150.0, speed_mps: float = 10.0,
                 altitude_m: float = 100.0, dt_s: float = 0.25, noise_m: float = DEMO_NOISE_M) -> None:
        try:
            lat, lon, alt = (float(v) for v in origin.split(","))
        except ValueError as exc:
            raise ConfigError(f"--origin {origin!r}: expected LAT,LON,ALT_AMSL, e.g. {SITL_HOME}") from exc
        if not (abs(lat) < 89.0 and abs(lon) <= 180.0):
            raise ConfigError(f"--origin {origin!r}: latitude must be in (-89, 89), longitude in [-180, 180]")
        self.lat0, self.lon0, self.ground_amsl_m = lat, lon, alt
        self.radius_m, self.speed_mps, self.altitude_m, self.dt_s = radius_m, speed_mps, altitude_m, dt_s
        self.noise_m = noise_m
        self.rng = np.random.default_rng(seed)
        self.follow: VehicleState | None = None

    def world_to_latlon(self, x_m: float, y_m: float) -> tuple[float, float]:
        lat, lon = offset_latlon(self.lat0, self.lon0, x_m, y_m)
        return float(lat), float(lon)

    def latlon_to_world(self, lat: float, lon: float) -> tuple[float, float]:
        x, y = east_north_m(self.lat0, self.lon0, lat, lon)
        return float(x), float(y)

    def steps(self) -> Iterator[Step]:
        k = 0
        while True:
            t = k * self.dt_s
            if self.follow is not None:       # closed loop: the truth is the simulator's vehicle
                x, y = self.latlon_to_world(self.follow.lat_deg, self.follow.lon_deg)
                yaw = math.pi / 2 - self.follow.heading_rad
                alt = max(0.0, self.follow.alt_amsl_m - self.ground_amsl_m)
            else:
                phase = self.speed_mps * t / self.radius_m
                x, y = self.radius_m * math.cos(phase), self.radius_m * math.sin(phase)
                yaw, alt = phase + math.pi / 2, self.altitude_m
            nx, ny = self.rng.normal(0.0, self.noise_m, 2)
            est = _Estimate(x + nx, y + ny, yaw, np.eye(2) * self.noise_m ** 2)
            yield Step(t, est, alt, None)
            k += 1


class ScenarioRun:
    """The env and an agent, run by the episode driver (``estimators.episode``); each estimate goes to the bridge.

    With ``follow_steps`` the env is instead rendered at the simulator's true vehicle (``env.external``): the
    camera is where the autopilot's vehicle is, the agent estimates from those frames.
    """

    def __init__(self, scenario: str, agent_name: str, seed: int, overrides: dict | None = None) -> None:
        try:
            import gymnasium as gym

            import aerial_loc_env.env  # noqa: F401  (importing the env registers the scenarios)
            from aerial_loc_env.estimators.episode import EpisodeDriver
            from aerial_loc_env.estimators.registry import make_agent
        except ImportError as exc:
            raise AerialLocError(
                f"aerial-loc mavlink: the environment or the agents are not available ({exc}); "
                "use --demo to stream a synthetic track") from exc
        try:
            self.env = gym.make(scenario, **(overrides or {}))
        except gym.error.Error as exc:
            raise ConfigError(f"--scenario {scenario!r}: {exc}; list them: aerial-loc scenarios") from exc
        self.agent = make_agent(agent_name)
        self.driver = EpisodeDriver(self.env, [self.agent])
        self.seed = seed
        self.episode = 0
        self.follow: VehicleState | None = None
        # estimates are in the database map's frame (what the estimator knows): lat/lon through its georeference;
        # the truth (follow mode) is placed through the ground's own (they differ by any georeference bias)
        self.orthomap = self.env.unwrapped.database
        self.ground_map = self.env.unwrapped.orthomap

    def steps(self, loop: bool) -> Iterator[Step]:
        """Each frame, the agent estimates on it (the first and the last frame too), then the env steps on
        that estimate (the driver's time line); ``loop`` starts the next episode (seed + 1) when one ends."""
        t0_s = 0.0
        while True:
            t_s = t0_s
            for rec in self.driver.episode(self.seed + self.episode):
                t_s = t0_s + rec.time_s
                yield Step(t_s, rec.estimates[0], float(rec.observation["altitude"][0]),
                           float(rec.observation["yaw"][0]), rec.error_m(0))
            if not loop:
                return
            self.episode += 1
            t0_s = t_s + float(self.driver.briefing.dt_s)     # simulated time keeps running across episodes

    def follow_steps(self, ground_amsl_m: float, *, pad_std_m: float = 0.5, pad_radius_m: float = math.inf,
                     sim_speedup: float = 1.0, cut: Callable[[], bool] | None = None) -> Iterator[Step | None]:
        """Frames at the simulator's true vehicle (``self.follow``, set by the caller from SIM_STATE).

        The camera frames at the scenario's rate (stream time: the monotonic time SIM_STATE arrived) while the
        vehicle is within the altitudes the agent estimates at (``Agent.altitude_range_m``: template matching
        down to where its template gets too small, others within a factor 2 of the scenario's altitude) with the
        footprint on the map; a frame whose *measured* altitude falls outside is not given to the agent (lost),
        as a companion computer goes by its altimeter. Before the first frame the fix is the take-off point (a
        surveyed pad, ``pad_std_m``), as a vehicle on the ground knows where it stands, while it is within
        ``pad_radius_m`` of the pad (beyond, e.g. a fixed wing's take-off run and climb, no fix); below that height
        later (landing) or off the map the fix is lost (the autopilot then lands on inertial navigation). While
        ``cut()`` holds (a vision-cut mission) the fix is withheld from the autopilot's position feed: the agent
        keeps its frames (its track stays continuous) and the step has source "cut". Yields None while no truth has
        come. Frame times and odometry are in the simulator's seconds: the truth's
        ``sim_time_s`` (SITL's boot time through SYSTEM_TIME), else its arrival scaled by ``sim_speedup`` (SITL
        ``--speedup``).
        """
        from aerial_loc_env.env.external import ExternalFlight, ExternalPose

        flight = ExternalFlight(self.env)
        pad: tuple[float, float] | None = None
        started = False
        last_frame: Step | None = None
        min_alt, max_alt = self.camera_altitude_range_m()
        # the first frame's costs (the map's image made, the whole-map shadows swept, the agent's levels built)
        # paid before the stream starts: the first frame comes when the vehicle enters the camera's range, and a
        # frame seconds late leaves the vehicle that far from where the agent's dead reckoning (one camera period
        # per frame) puts it, beyond its search window
        u = self.env.unwrapped
        flight.reset(ExternalPose(u.orthomap.width_m / 2.0, u.orthomap.height_m / 2.0, 0.0,
                                  float(u.scenario.flight.altitude_m), 0.0), seed=self.seed)
        self.agent.reset(flight.briefing, seed=self.seed)

        def lost(pose: ExternalPose, altitude_m: float, source: str = "lost") -> Step:
            """No fix: the last frame's estimate flagged lost (a held position sent as valid told the EKF the
            vehicle had stopped)."""
            held = last_frame.estimate if last_frame is not None else _Estimate(*pad, None, np.eye(2))
            est = _Estimate(held.x_m, held.y_m, None, np.asarray(held.cov_xy_m2), "lost")
            return Step(pose.t_s, est, altitude_m, pose.yaw_rad, math.hypot(pose.x_m - held.x_m, pose.y_m - held.y_m),
                        source)
        seen_s = math.nan
        while True:
            v = self.follow
            if v is None or v.received_mono_s == seen_s:    # no truth yet, or nothing new since the last step
                yield None
                continue
            seen_s = v.received_mono_s
            x, y = (float(np.ravel(c)[0]) for c in self.ground_map.latlon_to_world(v.lat_deg, v.lon_deg))
            t_s = v.sim_time_s if math.isfinite(v.sim_time_s) else v.received_mono_s * sim_speedup
            pose = ExternalPose(x, y, math.pi / 2 - v.heading_rad, v.alt_amsl_m - ground_amsl_m, t_s)
            if pad is None:
                pad = (x, y)
            high = min_alt <= pose.altitude_m <= max_alt
            airborne = high and flight.footprint_inside(pose)
            if not started and not airborne and math.hypot(x - pad[0], y - pad[1]) <= pad_radius_m:
                est = _Estimate(pad[0], pad[1], None, np.eye(2) * pad_std_m ** 2)
                yield Step(pose.t_s, est, max(0.0, pose.altitude_m), pose.yaw_rad, math.hypot(x - pad[0], y - pad[1]),
                           "pad")
                continue
            if not airborne:     # landing below the camera's range, or off the map: no fix (lost)
                yield lost(pose, max(0.0, pose.altitude_m))
                continue
            if not started or flight.due(pose.t_s):
                if not started:
                    obs, info = flight.reset(pose, seed=self.seed)
                    self.agent.reset(flight.briefing, seed=self.seed)
                    started = True
                else:
                    obs, info = flight.observe(pose)
                measured = float(obs["altitude"][0])
                if not min_alt <= measured <= max_alt:      # the altimeter says out of the agent's range
                    yield lost(pose, measured)
                    continue
                est = self.agent.step(obs, info if getattr(self.agent, "uses_ground_truth", False) else None)
                last_frame = Step(pose.t_s, est, float(obs["altitude"][0]), float(obs["yaw"][0]),
                                  math.hypot(est.x_m - x, est.y_m - y))
                yield dataclasses.replace(last_frame, source="cut") if cut is not None and cut() else last_frame
            else:
                yield None

    def camera_altitude_range_m(self) -> tuple[float, float]:
        """The altitudes (m above ground) at which follow mode gives the agent frames: its own range for this
        scenario's briefing (``Agent.altitude_range_m``)."""
        if self.env.unwrapped.briefing is None:       # the briefing exists from the first reset on
            self.env.reset(seed=self.seed)
        return tuple(float(v) for v in self.agent.altitude_range_m(self.env.unwrapped.briefing))

    def close(self) -> None:
        self.driver.close()
        self.env.close()


def status_line(t_sim_s: float, stats: SenderStats, error_m: float | None = None) -> str:
    q = stats.quality
    fix = "none" if q is None else ("3D" if q.fix_type == 3 else "no-fix")
    hacc = "-" if q is None or not q.usable else f"{q.h_acc_m:.1f}m"
    sent = " ".join(f"{k}={v}" for k, v in sorted(stats.sent.items()))
    if stats.dropped:
        sent += f" dropped={stats.dropped}"
    link = "up" if stats.link_up else "DOWN"
    err = "" if error_m is None else f"err={error_m:.1f}m "
    return (f"t={t_sim_s:7.1f}s {err}fix={fix} hacc={hacc} rate={stats.rate_hz:5.2f}Hz "
            f"jitter={stats.jitter_s * 1e3:4.1f}ms reset={stats.reset_counter} link={link} {sent}")


def ground_amsl_m(given: float | None, orthomap: Any, scenario: str) -> float:
    """The terrain height under the map: ``--ground-amsl-m``, else the map's own ``ground_amsl_m``.

    Why no silent default: a wrong height puts the EKF origin (SET_GPS_GLOBAL_ORIGIN) and every GPS_INPUT altitude
    that far off; sea level under a map at 584 m would put the EKF origin 584 m below the vehicle.
    """
    value = given if given is not None else getattr(orthomap, "ground_amsl_m", None)
    if value is None:
        raise ConfigError(f"--scenario {scenario}: its map declares no terrain height; give --ground-amsl-m "
                          "(metres above mean sea level of the ground under the map, e.g. 584 at ArduPilot "
                          "SITL's default home)")
    return check_ground_amsl_m(value)


def check_ground_amsl_m(value: float) -> float:
    """``--ground-amsl-m`` as a float, or a clear error outside ``GROUND_AMSL_RANGE_M``."""
    lo, hi = GROUND_AMSL_RANGE_M
    if not math.isfinite(float(value)) or not lo <= float(value) <= hi:
        raise ConfigError(f"--ground-amsl-m {value}: must be a finite height in [{lo:g}, {hi:g}] m AMSL "
                          "(the ground under the map)")
    return float(value)


def check_sim_speedup(value: float, option: str = "--sim-speedup") -> float:
    """The simulator's speedup as a float, or a clear error outside ``SIM_SPEEDUP_RANGE``."""
    lo, hi = SIM_SPEEDUP_RANGE
    if not (math.isfinite(value) and lo <= value <= hi):
        raise ConfigError(f"{option} {value}: must be in [{lo:g}, {hi:g}] (SITL's --speedup: simulated seconds "
                          "per real second; 1 = real time)")
    return float(value)


def run(args: argparse.Namespace, *, out=sys.stdout, should_stop: Callable[[], bool] = lambda: False,
        on_step: Callable[[Step], None] | None = None, vision_cut: Callable[[], bool] | None = None,
        on_sender: Callable[[MavlinkSender], None] | None = None) -> int:
    """Fly and stream until the episode ends, ``--duration-s`` passes, or Ctrl-C (returns 130).
    ``on_step`` sees each published step (a mission's record of the estimator's own error); while
    ``vision_cut()`` holds (follow mode) the fix is withheld from the autopilot; ``on_sender`` gets the sender
    once started (a mission's commands on the bridge's link, its latency record)."""
    if args.speed < 0 or not math.isfinite(args.speed):
        raise ConfigError(f"--speed {args.speed}: must be >= 0 (1 = real time, 0 = as fast as possible)")
    if not args.demo and not (args.scenario and args.agent):
        raise ConfigError("aerial-loc mavlink: give --scenario and --agent (or --demo for a synthetic track)")
    if args.demo and args.set:
        raise ConfigError("aerial-loc mavlink: --set overrides the --scenario's fields; --demo flies no scenario")
    check_sim_speedup(args.sim_speedup)
    config = sender_config(args)
    if args.demo:
        source: DemoTrack | ScenarioRun = DemoTrack(args.origin, args.seed)
        bridge = EstimateBridge(source.world_to_latlon, (0.0, 0.0), ground_amsl_m=source.ground_amsl_m)
        steps = source.steps()
    else:
        source = ScenarioRun(args.scenario, args.agent, args.seed,
                             parse_assignments(args.set, where="--set", example="flight.rate_hz=5"))
        om = source.orthomap      # lat/lon through the current episode's map (--loop may change it)
        ground = ground_amsl_m(args.ground_amsl_m, om, args.scenario)
        bridge = EstimateBridge(lambda x, y: source.orthomap.world_to_latlon(x, y),
                                (om.width_m / 2.0, om.height_m / 2.0), ground_amsl_m=ground)
        steps = (source.follow_steps(ground, pad_radius_m=args.pad_radius_m, sim_speedup=args.sim_speedup,
                                     cut=vision_cut)
                 if args.follow else source.steps(args.loop))
    sender = MavlinkSender(config, policy=FixPolicy(), origin=bridge.origin)
    tty = hasattr(out, "isatty") and out.isatty()
    t_sim, error_m = 0.0, None
    t_first: float | None = None      # follow mode: the first step's time on the simulator's clock
    follow_clock = args.follow and not args.demo      # step times: the simulator's clock
    code = 0
    try:
        sender.start()
        if on_sender is not None:
            on_sender(sender)
        t0 = time.monotonic()
        last_print = -math.inf
        for step in steps:
            if args.follow:      # the truth moves the camera; the sender keeps its own rate
                source.follow = sender.vehicle()
            if step is None:     # follow mode: no truth yet, or no frame due
                time.sleep(0.005)
                if (args.duration_s > 0 and time.monotonic() - t0 >= args.duration_s) or should_stop():
                    break
                continue
            if follow_clock and (t_first is None or step.time_s < t_first):
                # (the first truth samples may come before the simulator's own time is known: stamped by their
                # arrival, they lie far ahead of its boot seconds, and the status line counts from its first one)
                t_first = step.time_s
            t_sim = step.time_s - t_first if follow_clock else step.time_s
            error_m = step.error_m
            # pace simulated time against the monotonic clock (absolute, no drift); follow runs on the truth's
            if args.speed > 0 and not follow_clock:
                delay = t0 + t_sim / args.speed - time.monotonic()
                if delay > 0:
                    time.sleep(delay)
            fix = bridge.fix(step.estimate, time_s=step.time_s, altitude_m=step.altitude_m,
                             yaw_fallback_rad=step.yaw_fallback_rad)
            item = sender.publish(dataclasses.replace(fix, withheld=True) if step.source == "cut" else fix)
            if on_step is not None:
                on_step(step)
            while args.speed == 0 and sender.running and not sender.wait_taken(item.seq, 0.1):
                pass   # as fast as possible, but every frame's fix goes out once (at --rate-hz)
            now = time.monotonic()
            if not args.quiet and now - last_print >= 1.0:
                print(status_line(t_sim, sender.stats(), step.error_m), end="\r" if tty else "\n", file=out,
                      flush=True)
                last_print = now
            if sender.error is not None:
                raise AerialLocError(f"aerial-loc mavlink: the sender stopped: {sender.error}")
            if (args.duration_s > 0 and now - t0 >= args.duration_s) or should_stop():
                break
    except KeyboardInterrupt:
        code = 130
    finally:
        stats = sender.stats()   # before stop(): the final line shows the link as it was
        sender.stop()
        if isinstance(source, ScenarioRun):
            source.close()
    ending = "interrupted" if code == 130 else "done"
    print(("\n" if tty else "") + f"{ending}: {status_line(t_sim, stats, error_m)}", file=out, flush=True)
    return code


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    try:
        args = parser.parse_args(argv)
    except SystemExit as exc:   # --help or a usage error (argparse printed it)
        return int(exc.code or 0)
    return run(args)


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
