"""``aerial-loc pictures``: look at what the agents see before trusting any number.

Writes, into ``--out``:

- ``overview.png``: the map (downscaled) with a sample track, numbered camera footprints and the heading;
- ``overview_shadows.png``: the same with the episode's shadows (cast shadows from the height model, or
  drifting cloud shadows on maps without one);
- ``frame_NN_database.png`` / ``frame_NN_camera.png``: the shadow-free database patch and the camera frame
  (shadows, exposure, noise, vignetting) at a few poses of the track;
- ``frame_NN_pair.png``: database | camera | ground-truth shadow mask, side by side and labelled;
- ``contact_sheet.png``: all the pairs stacked;
- with ``--realism``, ``gap_<level>.png``: the map database at the true pose | the camera frame, for each kind
  of realistic map-camera gap alone (epoch change, relief displacement over tall buildings, the map's own sun,
  the map's own sensor) and all together (``AerialLoc/RealisticPaper-v3``); with ``--map``, the kinds that apply
  to that map (its acquisition by another sensor, the realistic camera, both), flown over it; with ``--pair``
  also ``gap_real_pair.png``, a real two-epoch pair in the same layout (what the simulated gap should look like).

``--readme-dir DIR`` (with ``--realism``, the default map and seed) also writes the README's pictures into ``DIR``
(``README_PICTURES``: smaller copies, the gap pictures as JPEG, so that the repository stays small); ``make
pictures`` redraws ``docs/img`` that way.
"""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

import cv2
import numpy as np

from aerial_loc_env.errors import AerialLocError, ConfigError
from aerial_loc_env.sensors.camera import CameraModel, Pose
from aerial_loc_env.sensors.render import CameraRenderer, Frame, Photometry

_OVERVIEW_MAX_PX = 1600
#: the README's pictures: (its file, the pictures' file it is made from, its width in px or None for the same);
#: a ``.jpg`` name is written as JPEG (``_README_JPEG_QUALITY``)
README_PICTURES = (("frames_0.png", "frame_00_pair.png", 1200), ("frames_2.png", "frame_02_pair.png", 1200),
                   ("overview.png", "overview.png", 860),
                   *((f"gap_{s}.jpg", f"gap_{s}.png", None)
                     for s in ("epoch", "relief", "database_sun", "acquisition", "realistic")))
_README_JPEG_QUALITY = 85
_TRACK_RGB = (255, 40, 40)
_FOOTPRINT_RGB = (255, 230, 0)


def _parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(prog="aerial-loc pictures", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", required=True, help="output folder (created if missing)")
    ap.add_argument("--map", help="an orthomap (GeoTIFF, image with world file, or .alm bundle); "
                                  "default: the procedural default city")
    ap.add_argument("--crs", help="--map: the CRS of its world file when no .prj / .aux.xml names it, "
                                  "e.g. EPSG:32633")
    ap.add_argument("--gsd", type=float, help="--map: ground metres per pixel of an image without georeference")
    ap.add_argument("--seed", type=int, default=0, help="seed of the track, sun, clouds and sensor noise")
    ap.add_argument("--altitude", type=float, default=200.0, help="flight altitude above ground, metres")
    ap.add_argument("--frames", type=int, default=4, help="number of camera frames along the track (1-12)")
    ap.add_argument("--realism", action="store_true",
                    help="also write gap_<level>.png: map patch | camera frame for each kind of realistic gap "
                         "(epoch change, relief, the map's own sun, the map's sensor, all of them); with --map, "
                         "the kinds that apply to that map, flown over it (RealMap-v2 at --altitude)")
    ap.add_argument("--pair", nargs=2, metavar=("EARLIER", "LATER"),
                    help="--realism: also gap_real_pair.png, a real two-epoch pair flown as RealPair-v2 (map = "
                         "EARLIER, camera over LATER) in the same layout, to set beside the simulated gap")
    ap.add_argument("--pair-gsd", type=float, help="--pair: ground metres per pixel of images without georeference")
    ap.add_argument("--readme-dir", metavar="DIR",
                    help="--realism: also write the README's pictures into DIR (smaller copies of some of --out's, "
                         "the gap pictures as JPEG; `make pictures`: docs/img)")
    return ap


def main(argv: list[str] | None = None) -> int:
    args = _parser().parse_args(argv)
    try:
        if (args.crs or args.gsd is not None) and not args.map:
            raise ConfigError("pictures: --crs and --gsd describe the file given with --map; give --map too")
        if (args.pair or args.pair_gsd is not None) and not args.realism:
            raise ConfigError("pictures: --pair and --pair-gsd add a picture to --realism; give --realism too")
        if args.pair_gsd is not None and not args.pair:
            raise ConfigError("pictures: --pair-gsd describes the images given with --pair; give --pair too")
        if args.readme_dir and (not args.realism or args.map or args.frames < 3):
            raise ConfigError("pictures: --readme-dir draws the README's pictures: give --realism, the default map "
                              "(no --map) and at least 3 --frames")
        written = write_pictures(Path(args.out), map_path=args.map, seed=args.seed, altitude_m=args.altitude,
                                 n_frames=args.frames, map_crs=args.crs, map_gsd_m=args.gsd)
        if args.realism:
            written += write_realism_pictures(Path(args.out), seed=args.seed, map_path=args.map, map_crs=args.crs,
                                              map_gsd_m=args.gsd, altitude_m=args.altitude,
                                              pair=None if not args.pair else (*args.pair, args.pair_gsd))
        if args.readme_dir:
            written += write_readme_pictures(Path(args.out), Path(args.readme_dir))
    except AerialLocError as exc:
        print(f"aerial-loc pictures: {exc}", file=sys.stderr)
        return 2
    for path in written:
        print(path)
    return 0


def write_readme_pictures(src: Path, dst: Path) -> list[Path]:
    """The README's pictures (``README_PICTURES``) in ``dst``, made from the pictures in ``src`` (those of
    ``write_pictures`` and ``write_realism_pictures``): resized to their width (area interpolation), the ``.jpg``
    ones as JPEG. Returns the written paths."""
    missing = [made_from for _, made_from, _ in README_PICTURES if not (Path(src) / made_from).is_file()]
    if missing:
        raise ConfigError(f"pictures: {src} lacks {', '.join(missing)}, which the README's pictures are made "
                          "from; write them first (aerial-loc pictures --out DIR --realism --frames 3 or more)")
    try:
        Path(dst).mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise ConfigError(f"pictures: cannot create the README's picture folder {dst}: {exc.strerror}") from exc
    written = []
    for name, made_from, width in README_PICTURES:
        bgr = cv2.imread(str(Path(src) / made_from), cv2.IMREAD_COLOR)
        if width is not None and bgr.shape[1] != width:
            height = round(bgr.shape[0] * width / bgr.shape[1])
            bgr = cv2.resize(bgr, (width, height), interpolation=cv2.INTER_AREA)
        params = [cv2.IMWRITE_JPEG_QUALITY, _README_JPEG_QUALITY] if name.endswith(".jpg") else []
        written.append(_write_bgr(Path(dst) / name, bgr, params))
    return written


def write_pictures(out: Path, *, map_path: str | None = None, seed: int = 0, altitude_m: float = 200.0,
                   n_frames: int = 4, orthomap=None, map_crs: str | None = None,
                   map_gsd_m: float | None = None) -> list[Path]:
    """Render the pictures (see the module doc) and return the written paths."""
    from aerial_loc_env.sensors.flight import FlightConfig, footprint_radius_m, sample_track
    from aerial_loc_env.world.maps.region import FlyableRegion
    from aerial_loc_env.world.shadows import ShadowConfig, apply_shading, sun_occlusion, upsample

    if not 1 <= n_frames <= 12:
        raise ConfigError(f"pictures: --frames = {n_frames} must be in [1, 12]")
    if not (math.isfinite(altitude_m) and 1.0 <= altitude_m <= 5000.0):
        raise ConfigError(f"pictures: --altitude = {altitude_m} must be in [1, 5000] metres")
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise ConfigError(f"pictures: cannot create the output folder {out}: {exc.strerror}") from exc
    if orthomap is None:
        orthomap = _load_map(map_path, crs=map_crs, gsd_m=map_gsd_m)
    rng = np.random.default_rng(seed)
    camera = CameraModel()
    flight = FlightConfig(altitude_m=altitude_m, duration_s=60.0)
    radius = footprint_radius_m(*camera.footprint_m(altitude_m))
    region = FlyableRegion(orthomap.width_m, orthomap.height_m, radius + 5.0, nodata=orthomap.nodata,
                           name=orthomap.name)
    track = sample_track(flight, region, rng)

    shadow_cfg = ShadowConfig(cloud_cover=0.0 if orthomap.dsm_m is not None else 0.35)
    sun = shadow_cfg.draw_sun(rng)
    shading = {"strength": shadow_cfg.draw_strength(rng), **shadow_cfg.shading_kwargs()}
    if orthomap.dsm_m is not None:
        occlusion = sun_occlusion(orthomap.dsm_m, orthomap.gsd_x_m, orthomap.gsd_y_m, sun,
                                  downsample=shadow_cfg.downsample)
        shadow_note = f"sun az {sun.azimuth_deg:.0f} deg, el {sun.elevation_deg:.0f} deg"
    else:
        occlusion = shadow_cfg.draw_clouds(rng, orthomap.width_m, orthomap.height_m)
        shadow_note = f"cloud shadows at t = 0 s (they drift), cover {shadow_cfg.cloud_cover:.0%}"
    renderer = CameraRenderer(orthomap, camera, Photometry(), noise_seed=rng)

    picks = np.linspace(0, len(track) - 1, n_frames + 2)[1:-1].round().astype(int)
    poses = [Pose(float(track.x_m[i]), float(track.y_m[i]), float(track.yaw_rad[i]),
                  float(track.altitude_m[i])) for i in picks]
    written: list[Path] = []

    # ---- overviews
    scale = min(1.0, _OVERVIEW_MAX_PX / max(orthomap.width_px, orthomap.height_px))
    size = (max(1, round(orthomap.width_px * scale)), max(1, round(orthomap.height_px * scale)))
    small = cv2.resize(np.asarray(orthomap.rgb), size, interpolation=cv2.INTER_AREA)
    if orthomap.dsm_m is not None:
        occ_small = cv2.resize(upsample(occlusion, (orthomap.height_px, orthomap.width_px)), size,
                               interpolation=cv2.INTER_AREA)
    else:
        to_world = np.array([[orthomap.width_m / size[0], 0.0, 0.5 * orthomap.width_m / size[0]],
                             [0.0, -orthomap.height_m / size[1], orthomap.height_m * (1 - 0.5 / size[1])]])
        occ_small = occlusion.occlusion_image(0.0, to_world, (size[1], size[0]))
    shaded_small = apply_shading(small, occ_small, shading["strength"], **shadow_cfg.shading_kwargs())
    for name, base, note in (("overview.png", small, "database"), ("overview_shadows.png", shaded_small,
                                                                     shadow_note)):
        img = _draw_track(base.copy(), orthomap, scale, track, poses, camera)
        img = _with_header(img, f"{orthomap.name}: {orthomap.width_m:.0f} x {orthomap.height_m:.0f} m, {note}; "
                                f"track {track.length_m:.0f} m at {altitude_m:.0f} m (red, dot = start); "
                                "camera footprints (yellow, arrow = heading)")
        written.append(_save(out / name, img))

    # ---- frames
    pairs = []
    for k, (pose, i) in enumerate(zip(poses, picks, strict=True)):
        database = renderer.database_patch(pose, strict=True)
        frame = renderer.render(pose, rng, occlusion, shading, t_s=float(track.t_s[i]),
                                speed_mps=float(track.speed_mps[i]), strict=True)
        written.append(_save(out / f"frame_{k:02d}_database.png", database))
        written.append(_save(out / f"frame_{k:02d}_camera.png", frame.image))
        pair = _pair(k, database, frame)
        written.append(_save(out / f"frame_{k:02d}_pair.png", pair))
        pairs.append(pair)
    gap = np.full((8, pairs[0].shape[1], 3), 255, np.uint8)
    sheet = np.concatenate([x for p in pairs for x in (p, gap)][:-1], axis=0)
    written.append(_save(out / "contact_sheet.png", sheet))
    return written


def _load_map(map_path: str | None, crs: str | None = None, gsd_m: float | None = None):
    if map_path is None:
        from aerial_loc_env.world.city import default_city

        return default_city()
    from aerial_loc_env.world.maps.io import load_orthomap

    if not Path(map_path).exists():
        raise ConfigError(f"pictures: --map {map_path} does not exist")
    return load_orthomap(map_path, crs=crs, gsd_m=gsd_m)


def _world_to_small(orthomap, scale: float, xy: np.ndarray) -> np.ndarray:
    """World metres (..., 2) -> overview pixel coordinates for cv2 drawing (pixel centres at integers)."""
    u = (xy[..., 0] / orthomap.gsd_x_m) * scale - 0.5
    v = (orthomap.height_px - xy[..., 1] / orthomap.gsd_y_m) * scale - 0.5
    return np.stack([u, v], axis=-1)


def _draw_track(img: np.ndarray, orthomap, scale: float, track, poses: list[Pose],
                camera: CameraModel) -> np.ndarray:
    shift = 4  # sub-pixel drawing: coordinates in 1/16 px

    def to_int(p: np.ndarray) -> np.ndarray:
        return np.rint(p * (1 << shift)).astype(np.int32)

    thick = max(1, round(img.shape[1] / 800))
    line = _world_to_small(orthomap, scale, np.stack([track.x_m, track.y_m], axis=-1))
    cv2.polylines(img, [to_int(line)], False, _TRACK_RGB, thick, cv2.LINE_AA, shift)
    start = _world_to_small(orthomap, scale, np.array([track.x_m[0], track.y_m[0]]))
    cv2.circle(img, tuple(int(c) for c in to_int(start)), 5 * thick << shift, _TRACK_RGB, -1, cv2.LINE_AA, shift)
    for k, pose in enumerate(poses):
        corners = camera.footprint_corners_m(*pose)
        poly = _world_to_small(orthomap, scale, corners)
        cv2.polylines(img, [to_int(poly)], True, _FOOTPRINT_RGB, thick, cv2.LINE_AA, shift)
        top_mid = _world_to_small(orthomap, scale, corners[:2].mean(axis=0))   # the edge ahead of the vehicle
        centre = _world_to_small(orthomap, scale, np.array(pose[:2]))
        cv2.arrowedLine(img, tuple(int(c) for c in to_int(centre)), tuple(int(c) for c in to_int(top_mid)),
                        _FOOTPRINT_RGB, thick, cv2.LINE_AA, shift, 0.25)
        org = poly.min(axis=0) + np.array([2.0, -4.0])
        _text(img, str(k), (int(org[0]), int(max(org[1], 12))), 0.6 * thick, _FOOTPRINT_RGB)
    return img


def _pair(k: int, database: np.ndarray, frame: Frame) -> np.ndarray:
    mask = np.where(frame.shadow_mask[..., None], np.uint8(70), np.uint8(235)).repeat(3, axis=2)
    gap = np.full((database.shape[0], 6, 3), 255, np.uint8)
    row = np.concatenate([database, gap, frame.image, gap, mask], axis=1)
    head = np.full((28, row.shape[1], 3), 255, np.uint8)
    w = database.shape[1] + gap.shape[1]
    p = frame.pose
    _text(head, f"{k}: database patch", (6, 20), 0.55, (0, 0, 0))
    _text(head, f"camera: x {p.x_m:.0f} m, y {p.y_m:.0f} m, yaw {math.degrees(p.yaw_rad):.0f} deg, "
                f"alt {p.altitude_m:.0f} m", (w + 6, 20), 0.55, (0, 0, 0))
    _text(head, f"true shadow mask ({frame.shadow_fraction:.0%} of the frame)", (2 * w + 6, 20), 0.55, (0, 0, 0))
    return np.concatenate([head, row], axis=0)


def _text(img: np.ndarray, text: str, org: tuple[int, int], scale: float, rgb: tuple[int, int, int]) -> None:
    """Text with a contrasting outline, readable on any background."""
    outline = (0, 0, 0) if sum(rgb) > 380 else (255, 255, 255)
    thick = max(1, round(scale * 1.6))
    cv2.putText(img, text, org, cv2.FONT_HERSHEY_SIMPLEX, scale, outline, thick + 2, cv2.LINE_AA)
    cv2.putText(img, text, org, cv2.FONT_HERSHEY_SIMPLEX, scale, rgb, thick, cv2.LINE_AA)


def _with_header(img: np.ndarray, text: str) -> np.ndarray:
    """The image under a white banner carrying ``text`` (never drawn over the map itself)."""
    scale = float(np.clip(img.shape[1] / 1900, 0.4, 0.8))
    (_, h), _ = cv2.getTextSize(text, cv2.FONT_HERSHEY_SIMPLEX, scale, 1)
    head = np.full((h + 16, img.shape[1], 3), 255, np.uint8)
    cv2.putText(head, text, (8, h + 8), cv2.FONT_HERSHEY_SIMPLEX, scale, (0, 0, 0), 1, cv2.LINE_AA)
    return np.concatenate([head, img], axis=0)


def _save(path: Path, rgb: np.ndarray) -> Path:
    return _write_bgr(path, cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))


def _write_bgr(path: Path, bgr: np.ndarray, params: list[int] | None = None) -> Path:
    if not cv2.imwrite(str(path), bgr, params or []):
        raise ConfigError(f"pictures: could not write {path} (check the folder is writable)")
    return path


# ------------------------------------------------------------------------------------------ realism levels
#: (file stem, title, scenario id, overrides, frame choice): one picture per kind of map/camera gap, each with
#: only that kind switched on over the paper's shadow-free setting (``realism_levels`` fills the sections in
#: from the realistic presets, so the pictures show what those presets fly).
_QUIET = {"shadows.strength_range": [0.0, 0.0]}


def realism_levels() -> list[tuple[str, str, str, dict, str]]:
    """The realism levels shown by ``write_realism_pictures``, built from the realistic presets' specs."""
    from aerial_loc_env.config import config_to_dict
    from aerial_loc_env.env import load_scenario
    from aerial_loc_env.env.scenarios import SECTIONS

    real = load_scenario("AerialLoc/RealisticPaper-v3").to_dict()
    season = load_scenario("AerialLoc/SeasonChange-v3").to_dict()
    # relief alone: Downtown with every other part of the gap back at its default (off)
    relief = {name: config_to_dict(SECTIONS[name]()()) for name in
              ("epoch", "database", "gimbal", "altimeter", "exposure", "haze", "photometry")}
    relief["shadows"] = {"strength_range": [0.0, 0.0], "database_sun_deg": None}
    sun = real["shadows"]["database_sun_deg"]
    return [
        ("paper", "the paper's setting: shadow-free map | camera with cast shadows (PaperShadows)",
         "AerialLoc/PaperShadows-v2", {}, "middle"),
        ("epoch", "epoch change only: map of epoch A | camera over epoch B (SeasonChange's rates)",
         "AerialLoc/PaperNoShadows-v2", {**_QUIET, "epoch": season["epoch"]}, "middle"),
        ("relief", "relief only: affine map patch | perspective camera, tall buildings at the frame edge "
                   "(Downtown)", "AerialLoc/Downtown-v3", relief, "relief"),
        ("database_sun", f"map with another sun's shadows (az {sun[0]:.0f}, el {sun[1]:.0f} deg) | camera "
                         "with the flight's sun", "AerialLoc/PaperShadows-v2",
         {"shadows.database_sun_deg": sun}, "middle"),
        ("acquisition", "map acquired by another sensor (GSD, blur, JPEG, colour, haze, lean, georeference "
                        "bias) | camera", "AerialLoc/PaperNoShadows-v2", {**_QUIET, "database": real["database"]},
         "middle"),
        ("realistic", "everything: RealisticPaper-v3 map | camera", "AerialLoc/RealisticPaper-v3", {}, "middle"),
    ]


def map_realism_levels(map_path: str, *, crs: str | None = None, gsd_m: float | None = None,
                       altitude_m: float = 200.0) -> tuple[list[tuple[str, str, str, dict, str]], list[str]]:
    """The realism levels that apply to a user's map, flown over it (``AerialLoc/RealMap-v2`` with the pictures'
    600 x 400 camera at ``altitude_m``, clouds off unless all is on), and the levels left out with why: the epoch
    change needs the city's land cover and height model, relief and the map's own sun a height model, building
    lean in the acquisition too (it is left out of the acquisition on a map without one)."""
    from aerial_loc_env.env import load_scenario

    orthomap = _load_map(map_path, crs=crs, gsd_m=gsd_m)
    real = load_scenario("AerialLoc/RealisticPaper-v3").to_dict()
    has_dsm = orthomap.dsm_m is not None
    base: dict = {"map": {"kind": "file", "path": str(map_path), **({"crs": crs} if crs else {}),
                          **({"gsd_m": gsd_m} if gsd_m is not None else {})},
                  "flight.altitude_m": float(altitude_m), "camera": {"width_px": 600, "height_px": 400}}
    quiet = {"shadows.cloud_cover": 0.0}
    database = dict(real["database"]) if has_dsm else {**real["database"], "lean_deg": 0.0}
    camera = {name: real[name] for name in ("gimbal", "altimeter", "exposure", "haze", "photometry")}
    name = orthomap.name
    levels = [
        ("acquisition", f"{name}: map acquired by another sensor (GSD, blur, JPEG, colour, haze, georeference bias"
                        f"{', lean' if has_dsm else ''}) | camera", "AerialLoc/RealMap-v2",
         {**base, **quiet, "database": database}, "middle"),
        ("camera", f"{name}: map | realistic camera (gimbal 0.3 deg, heading 1 deg, baro 2 m, auto-exposure, haze, "
                   "photometry)", "AerialLoc/RealMap-v2", {**base, **quiet, **camera}, "middle"),
        ("realistic", f"{name}: everything that applies: another sensor's map | realistic camera, cloud shadows",
         "AerialLoc/RealMap-v2", {**base, "database": database, **camera}, "middle"),
    ]
    left_out = ["epoch (needs the procedural city's land cover and height model)"]
    if has_dsm:
        levels.insert(2, ("relief", f"{name}: relief only: affine map patch | perspective camera",
                          "AerialLoc/RealMap-v2", {**base, **quiet, "perspective": {"enabled": True}}, "relief"))
    else:
        left_out += ["relief and database_sun (need a height model; the map has none)"]
    return levels, left_out


def pair_level(path_a: str, path_b: str, gsd_m: float | None = None) -> tuple[str, str, str, dict, str]:
    """The realism level of a real two-epoch pair: ``AerialLoc/RealPair-v2`` over it (map = the earlier image,
    camera over the later one), to be seen beside the simulated levels in the same layout."""
    pair = {"path_a": str(path_a), "path_b": str(path_b), **({"gsd_m": gsd_m} if gsd_m is not None else {})}
    a, b = (f"{Path(p).parent.name}/{Path(p).name}" for p in (path_a, path_b))
    return ("real_pair", f"a real two-epoch pair: map = {a} (earlier) | camera over {b} (later), RealPair-v2",
            "AerialLoc/RealPair-v2", {"map": pair}, "middle")


def write_realism_pictures(out: Path, *, seed: int = 0, levels: list | None = None, map_path: str | None = None,
                           map_crs: str | None = None, map_gsd_m: float | None = None,
                           altitude_m: float = 200.0,
                           pair: tuple[str, str, float | None] | None = None) -> list[Path]:
    """``gap_<level>.png``: map patch at the true pose | camera frame, one per realism level, labelled: the
    procedural city's levels (``realism_levels``), or with ``map_path`` those that apply to that map
    (``map_realism_levels``; the others are named on stderr); with ``pair`` (earlier, later, GSD or None) also
    ``gap_real_pair.png`` (``pair_level``)."""
    from aerial_loc_env.env import AerialLocEnv, load_scenario

    if levels is None and map_path is not None:
        levels, left_out = map_realism_levels(map_path, crs=map_crs, gsd_m=map_gsd_m, altitude_m=altitude_m)
        print(f"aerial-loc pictures --realism: on {map_path}, left out: {'; '.join(left_out)}", file=sys.stderr)
    levels = realism_levels() if levels is None else list(levels)
    Path(out).mkdir(parents=True, exist_ok=True)
    if pair is not None:
        levels.append(pair_level(*pair))
    written = []
    for stem, title, sid, overrides, choice in levels:
        env = AerialLocEnv(load_scenario(sid, overrides))
        try:
            obs, info = env.reset(seed=seed)
            frames = [(obs["image"], info["true_pose"])]
            done = False
            while not done:
                obs, _r, terminated, truncated, info = env.step(np.zeros(2, np.float32))
                frames.append((obs["image"], info["true_pose"]))
                done = terminated or truncated
            pick = _relief_frame(env, frames) if choice == "relief" else len(frames) // 2
            image, truth = frames[pick]
            pose = Pose(*(float(v) for v in truth))
            database = CameraRenderer(env.briefing.orthomap, env.camera, Photometry.ideal(),
                                      strict=False).database_patch(pose)
        finally:
            env.close()
        gap = np.full((image.shape[0], 6, 3), 255, np.uint8)
        row = np.concatenate([database, gap, image], axis=1)
        head = np.full((28, row.shape[1], 3), 255, np.uint8)
        _text(head, "map database at the true pose", (6, 20), 0.55, (0, 0, 0))
        _text(head, f"camera frame (x {pose.x_m:.0f} m, y {pose.y_m:.0f} m, alt {pose.altitude_m:.0f} m)",
              (database.shape[1] + 12, 20), 0.55, (0, 0, 0))
        written.append(_save(out / f"gap_{stem}.png", _with_header(np.concatenate([head, row], axis=0), title)))
    return written


def _relief_frame(env, frames: list) -> int:
    """The frame whose footprint edge holds the tallest buildings (relief displacement is largest there)."""
    om = env.orthomap
    cam = env.camera
    w, h, t = 0.95 * cam.width_px, 0.95 * cam.height_px, np.linspace(0.05, 0.95, 40)
    edge = np.concatenate([np.stack([t * cam.width_px, np.full_like(t, 0.05 * cam.height_px)], axis=1),
                           np.stack([t * cam.width_px, np.full_like(t, h)], axis=1),
                           np.stack([np.full_like(t, 0.05 * cam.width_px), t * cam.height_px], axis=1),
                           np.stack([np.full_like(t, w), t * cam.height_px], axis=1)])   # a band 5 % inside
    best, score = 0, -1.0
    for i, (_img, truth) in enumerate(frames):
        uv = cam.project_pixels(om, edge, *(float(t) for t in truth))[0]
        cols = np.clip(np.rint(uv[:, 0]).astype(int), 0, om.width_px - 1)
        rows = np.clip(np.rint(uv[:, 1]).astype(int), 0, om.height_px - 1)
        s = float(np.percentile(np.asarray(om.dsm_m)[rows, cols], 90))
        if s > score:
            best, score = i, s
    return best
