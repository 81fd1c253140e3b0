"""The appearance-gap statistics (benchmark/gap.py) on inputs whose answer is known, on real files, and on
the real two-epoch pairs beside the project."""

from __future__ import annotations

import json
import math

import cv2
import numpy as np
import pytest
from shared_helpers import SHARED_DATA

from aerial_loc_env.benchmark import gap
from aerial_loc_env.benchmark.store import finite_or_null
from aerial_loc_env.errors import ConfigError

PAIRS = SHARED_DATA / "pairs" / "levir-cd"


def texture(h: int, w: int, seed: int = 0) -> np.ndarray:
    """A smooth random RGB texture (blobs of a few pixels, like ground seen from above)."""
    g = np.random.default_rng(seed)
    img = cv2.GaussianBlur(g.normal(0.0, 1.0, (h, w, 3)).astype(np.float32), (0, 0), 2.0)
    img = (img - img.min()) / (img.max() - img.min()) * 255.0
    return img.astype(np.uint8)


def test_identical_windows_are_a_perfect_match():
    cfg = gap.GapConfig()
    img = texture(440, 640)
    windows = gap.pair_windows(img, img, cfg, 0.5)
    assert len(windows) == 4   # (640 - 40) // 300 x (440 - 40) // 200
    for cam, db in windows:
        s = gap.window_stats(cam, db, cfg)
        assert s["ncc"] == pytest.approx(1.0, abs=1e-9)
        assert s["bit_agreement"] == 1.0
        assert s["template_within"] == 1.0
        assert s["peak_margin"] > 0.0 and s["psr"] > 3.0
        assert s["orb_inlier_ratio"] > 0.9


def test_image_against_noise_is_unrelated():
    """NCC of a texture against i.i.d. noise has std 1/sqrt(n); each bit agrees with probability 1/2 up to
    the noise's ties (1/256), so agreement is binomial(n_bits, ~1/2)/n_bits: 4 sigma tolerances."""
    cfg = gap.GapConfig()
    img = texture(300, 400)
    noise = np.random.default_rng(1).integers(0, 256, img.shape, dtype=np.uint8)
    windows = gap.pair_windows(img, noise, cfg, 0.5)
    for cam, db in windows:
        s = gap.window_stats(cam, db, cfg)
        n = cam.shape[0] * cam.shape[1]
        assert abs(s["ncc"]) < 4.0 / math.sqrt(n)
        assert abs(s["bit_agreement"] - 0.5) < 4.0 * 0.5 / math.sqrt(cfg.n_bits) + 1.0 / 256
        assert s["peak_margin"] < 0.05
    fractions = gap.summarize([gap.window_stats(c, d, cfg) for c, d in windows])
    assert fractions["template_within"]["mean"] <= 0.5


@pytest.mark.parametrize(("shift_px", "within"), [(0, 1.0), (3, 1.0), (4, 1.0), (5, 0.0), (12, 0.0)])
def test_template_success_radius(shift_px, within):
    """The later epoch displaced by ``shift_px`` at 0.5 m/px: the peak sits at the shift, within 2 m iff
    shift * 0.5 <= 2."""
    cfg = gap.GapConfig()
    img = texture(340, 440, seed=2)
    later = np.roll(img, shift_px, axis=1)
    for cam, db in gap.pair_windows(img, later, cfg, 0.5):
        assert gap.window_stats(cam, db, cfg)["template_within"] == within


def test_surface_statistics_by_hand():
    s = np.zeros((41, 41), np.float32)
    s[20, 20] = 1.0
    s[0, 0] = 0.5
    out = gap.surface_stats(s, 0.5, 2.0)
    yy, xx = np.mgrid[0:41, 0:41]
    side = s[np.hypot(yy - 20, xx - 20) > 4.0]   # the side lobe: beyond 2 m = 4 px of the peak
    assert out["peak_margin"] == pytest.approx(0.5)
    assert out["psr"] == pytest.approx((1.0 - side.mean()) / side.std(), rel=1e-3)
    assert out["template_within"] == 1.0
    s[20, 20], s[20, 30] = 0.0, 1.0
    assert gap.surface_stats(s, 0.5, 2.0)["template_within"] == 0.0


def test_bad_windows_are_clear_errors():
    cfg = gap.GapConfig()
    with pytest.raises(ConfigError, match="must be 340 x 240"):
        gap.window_stats(np.zeros((200, 300)), np.zeros((200, 300)), cfg)
    with pytest.raises(ConfigError, match="share one pixel grid"):
        gap.pair_windows(np.zeros((300, 300, 3)), np.zeros((300, 301, 3)), cfg, 0.5)
    with pytest.raises(ConfigError, match="too small"):
        gap.pair_windows(np.zeros((100, 100, 3)), np.zeros((100, 100, 3)), cfg, 0.5)
    with pytest.raises(ConfigError, match="n_bits"):
        gap.gap_config(n_bits=0)


@pytest.mark.parametrize("where", ["camera", "database"])
@pytest.mark.parametrize("fill", ["all", "one"])
def test_windows_with_non_finite_pixels_are_refused_not_scored(where: str, fill: str):
    """NaN compares false, so an all-NaN pair scored as identical order (bit agreement 1.0): refused instead."""
    cfg = gap.GapConfig()
    cam = texture(200, 300)[..., 0].astype(np.float32)         # grey windows: one value per pixel
    db = texture(240, 340, seed=1)[..., 0].astype(np.float32)
    target = cam if where == "camera" else db
    if fill == "all":
        target[:] = np.nan
    else:
        target[7, 9] = np.inf
    bad = target.size if fill == "all" else 1
    with pytest.raises(ConfigError, match=rf"the {where} window has {bad} of {target.size} pixels that are not "
                                          r"finite .*leave out windows that touch no-data"):
        gap.window_stats(cam, db, cfg)


def _c3(rgb: tuple[int, int, int]) -> float:
    return math.atan2(rgb[2], max(rgb[0], rgb[1], 1)) * 2.0 / math.pi


def _luminance(rgb: tuple[int, int, int]) -> float:
    return float(cv2.cvtColor(np.uint8([[rgb]]), cv2.COLOR_RGB2GRAY)[0, 0])


@pytest.mark.parametrize(("lit", "dark"), [((150, 140, 110), (40, 45, 60)),     # bluish shadow on warm ground
                                           ((120, 130, 140), (30, 60, 40))])    # dark vegetation on grey
def test_camera_colour_statistics_of_a_known_two_class_window(lit, dark):
    """Half the window one colour, half another: Otsu splits the halves, the dark half is the class of the
    higher shadow index, and the statistics are the two colours' c3 difference and luminance ratio."""
    img = np.empty((40, 60, 3), np.uint8)
    img[:, :30], img[:, 30:] = lit, dark
    got = gap.camera_colour_stats(img)
    assert got["dark_c3_shift"] == pytest.approx(_c3(dark) - _c3(lit), abs=1e-6)
    assert got["dark_luma_ratio"] == pytest.approx(_luminance(dark) / _luminance(lit), abs=1e-9)
    assert (got["dark_c3_shift"] > 0) == (lit == (150, 140, 110))      # only the sky-lit shadow is bluer
    assert got == gap.camera_colour_stats(img.astype(np.float32))      # float windows as their bytes


def test_camera_colour_statistics_need_a_colour_window_with_two_classes():
    cfg = gap.GapConfig()
    img = texture(200, 300, seed=5)
    m = cfg.margin_px(cfg.gsd_m)
    database = cv2.copyMakeBorder(img, m, m, m, m, cv2.BORDER_REFLECT)
    grey = gap.window_stats(cv2.cvtColor(img, cv2.COLOR_RGB2GRAY), database, cfg)
    colour = gap.window_stats(img, database, cfg)
    assert all(math.isnan(grey[s]) for s in gap.CAMERA_STATS)
    assert all(math.isfinite(colour[s]) for s in gap.CAMERA_STATS)
    assert {s: grey[s] for s in gap.STATS} == {s: colour[s] for s in gap.STATS}    # the gap itself is on luma
    assert all(math.isnan(v) for v in gap.camera_colour_stats(np.full((20, 30, 3), 90, np.uint8)).values())
    summary = gap.summarize([grey, colour])
    assert summary["ncc"]["n"] == 2 and summary["dark_c3_shift"]["n"] == 1
    assert summary["dark_c3_shift"]["median"] == colour["dark_c3_shift"]
    assert gap.summarize([grey])["dark_luma_ratio"]["n"] == 0
    table = gap.gap_table([("grey", gap.summarize([grey]))])
    assert table.splitlines()[-1].endswith("| - | - |")


def test_photometric_statistics_of_a_camera_window_that_is_the_map_under_gain_offset_and_noise():
    """C = k D + b + n (noise n independent of D): the luma ratio is mean C / mean D, the contrast ratio
    sqrt(k^2 + var n / var D) and the SSD residual ((k - 1)^2 var D + var n + (mean C - mean D)^2) / var D, from the
    windows' own moments; identical windows give 1, 1 and 0."""
    rng = np.random.default_rng(4)
    d = rng.uniform(40.0, 200.0, (100, 150))
    n = rng.normal(0.0, 6.0, d.shape)
    n -= n.mean()
    c = 0.6 * d + 20.0 + n
    got = gap.photometric_stats(c, d)
    var_d, cov = d.var(), np.mean((d - d.mean()) * (n - n.mean()))
    assert got["luma_ratio"] == pytest.approx(c.mean() / d.mean(), rel=1e-12)
    assert got["contrast_ratio"] == pytest.approx(np.sqrt(0.36 + (n.var() + 1.2 * cov) / var_d), rel=1e-9)
    expected_ssd = (0.16 * var_d + n.var() - 0.8 * cov + (c.mean() - d.mean()) ** 2) / var_d
    assert got["ssd_residual"] == pytest.approx(expected_ssd, rel=1e-9)
    assert gap.photometric_stats(d, d) == {"luma_ratio": 1.0, "contrast_ratio": 1.0, "ssd_residual": 0.0}
    assert all(math.isnan(v) for v in gap.photometric_stats(d, np.full_like(d, 90.0)).values())
    cfg = gap.GapConfig()
    m = cfg.margin_px(cfg.gsd_m)
    img = texture(200, 300, seed=5)
    darker = (img * 0.5).astype(np.uint8)
    stats = gap.window_stats(darker, cv2.copyMakeBorder(img, m, m, m, m, cv2.BORDER_REFLECT), cfg)
    assert stats["luma_ratio"] == pytest.approx(0.5, abs=0.01) and stats["contrast_ratio"] == pytest.approx(0.5,
                                                                                                           abs=0.01)
    table = gap.gap_table([("half", gap.summarize([stats]))], stats=gap.PHOTO_STATS)
    assert table.splitlines()[0] == "| source | windows | camera / map luma | camera / map contrast | SSD residual |"


def test_a_single_image_gives_its_colour_statistics_window_by_window(tmp_path, capsys):
    """``--image PATH GSD``: a 400 x 300 m image at 1 m/px in 150 x 100 m windows (2 x 3 of them, centred), each
    scored by ``camera_colour_stats`` on the windows cut from the image; the gap columns stay empty."""
    img = texture(300, 400, seed=7)
    img[:, 200:] //= 3                                    # a dark half: both classes in the windows that cross it
    path = tmp_path / "tile.png"
    cv2.imwrite(str(path), cv2.cvtColor(img, cv2.COLOR_RGB2BGR))
    cfg = gap.GapConfig(gsd_m=1.0)
    windows, gsd = gap.image_colour_windows(path, cfg, gsd_m=1.0)
    assert gsd == 1.0 and len(windows) == 6
    expected = [gap.camera_colour_stats(img[y:y + 100, x:x + 150]) for y in (0, 100, 200) for x in (50, 200)]
    assert windows == expected
    out = tmp_path / "gap.json"
    from aerial_loc_env.cli import main

    assert main(["gap", "--gsd", "1", "--image", str(path), "1.0", "--json", str(out)]) == 0
    row = next(line for line in capsys.readouterr().out.splitlines() if line.startswith("| tile.png"))
    assert row.startswith("| tile.png (image) | 6 | - | - | - | - | - | - | ")
    data = json.loads(out.read_text())
    assert data["images"]["tile.png (image)"]["windows"] == json.loads(json.dumps(finite_or_null(expected)))
    assert main(["gap", "--image", str(path), "1.0", "--window-m", "500", "100"]) == 2    # wider than the image
    assert "--window-m" in capsys.readouterr().err
    assert main(["gap", "--image", str(tmp_path / "none.png"), "1.0"]) == 2
    assert "no such image file" in capsys.readouterr().err
    assert main(["gap", "--image", str(path), "1.0", "extra"]) == 2
    assert "PATH [GSD]" in capsys.readouterr().err
    island = np.zeros((300, 400, 3), np.uint8)            # black no-data around a 100 x 100 m patch of ground
    island[100:200, 150:250] = img[100:200, 150:250] // 2 + 60
    cv2.imwrite(str(tmp_path / "island.png"), island)
    assert main(["gap", "--image", str(tmp_path / "island.png"), "1.0"]) == 2
    assert "touches no-data; use a smaller window" in capsys.readouterr().err
    assert main(["gap", "--gsd", "1", "--image", str(tmp_path / "island.png"), "1.0", "--window-m", "50", "50"]) == 0


def test_pairs_from_files_and_the_command(tmp_path, capsys):
    """Real PNG files on disk, found as A/ and B/, through ``aerial-loc gap`` with --json."""
    for sub in ("A", "B"):
        (tmp_path / "pairs" / sub).mkdir(parents=True)
    img = texture(440, 640, seed=3)
    cv2.imwrite(str(tmp_path / "pairs" / "A" / "x.png"), img)
    cv2.imwrite(str(tmp_path / "pairs" / "B" / "x.png"), img)
    out = tmp_path / "gap.json"
    from aerial_loc_env.cli import main

    assert main(["gap", "--pairs-dir", str(tmp_path / "pairs"), "--pair-gsd", "0.5", "--json", str(out)]) == 0
    text = capsys.readouterr().out
    assert "| pairs/x.png | 4 | 1.00 (1.00-1.00) | 1.00 (1.00-1.00)" in text
    data = json.loads(out.read_text())
    assert data["real_spread"]["template_within"] == [1.0, 1.0]
    assert set(data["real_spread"]) == set(gap.ALL_STATS)
    before = out.read_bytes()
    assert main(["gap", "--pairs-dir", str(tmp_path / "pairs"), "--pair-gsd", "0.5", "--json", str(out)]) == 2
    assert out.read_bytes() == before and "exists" in capsys.readouterr().err
    assert main(["gap", "--pair", str(tmp_path / "pairs" / "A" / "x.png"),
                 str(tmp_path / "pairs" / "B" / "x.png")]) == 2   # no georeference and no --pair-gsd
    assert "gsd_m" in capsys.readouterr().err


def test_scenario_frame_and_database_align_at_the_true_pose():
    """Without shadows and sensor effects the camera frame is the database at the true pose: the statistics
    must say so (this checks the database window's geometry, margin included)."""
    ideal = {"exposure_std": 0.0, "white_balance_std": 0.0, "gamma_std": 0.0, "read_noise_dn": 0.0,
             "shot_noise_gain": 0.0, "vignetting": 0.0, "exposure_time_s": 0.0}
    flat = gap.scenario_gap("AerialLoc/Small-v3", {"shadows.strength_range": [0.0, 0.0], "photometry": ideal},
                            seeds=[0], stride=15)
    assert len(flat) == 5   # 61 frames, every 15th
    s = gap.summarize(flat)
    assert s["ncc"]["median"] > 0.97 and s["bit_agreement"]["median"] > 0.9
    assert s["template_within"]["mean"] == 1.0
    shaded = gap.summarize(gap.scenario_gap("AerialLoc/Small-v3", seeds=[0], stride=15))
    assert shaded["ncc"]["median"] < s["ncc"]["median"]


def test_map_bias_and_gimbal_error_are_scored_apart_from_appearance():
    """A co-registered pair cannot show a map's georeference bias nor a gimbal's tilt: the scenario's database
    patch is taken where the map shows what the tilted camera sees, so a 4 m bias and a 1 deg gimbal (3 m at
    the frame centre from 200 m) leave the ideal frame a perfect match, peak within 2 m included."""
    ideal = {"exposure_std": 0.0, "white_balance_std": 0.0, "gamma_std": 0.0, "read_noise_dn": 0.0,
             "shot_noise_gain": 0.0, "vignetting": 0.0, "exposure_time_s": 0.0}
    over = {"shadows.strength_range": [0.0, 0.0], "photometry": ideal, "database.georef_bias_m": [3.0, -2.6],
            "gimbal.roll_pitch_std_deg": 1.0}
    s = gap.summarize(gap.scenario_gap("AerialLoc/Small-v3", over, seeds=[0, 1], stride=15))
    assert s["template_within"]["mean"] == 1.0
    assert s["ncc"]["median"] > 0.95


@pytest.mark.slow
@pytest.mark.skipif(not PAIRS.is_dir(), reason=f"real two-epoch pairs not available ({PAIRS} is absent: they "
                                              "live beside the project, never in it)")
def test_real_pairs_are_far_less_alike_than_the_paper_scenario():
    """The LEVIR-CD pairs (0.5 m/px, years apart): their README measures NCC ~0.49 and bit agreement ~0.67;
    every pair must sit well below identity and well above unrelated."""
    for a, b in gap.pairs_in(PAIRS):
        s = gap.summarize(gap.pair_gap(a, b, gsd_m=0.5))
        assert 0.25 < s["ncc"]["median"] < 0.7, a.name
        assert 0.55 < s["bit_agreement"]["median"] < 0.75, a.name
        assert 0.0 < s["template_within"]["mean"] <= 1.0, a.name


def test_realism_pictures_show_map_and_camera_side_by_side(tmp_path):
    """One labelled picture per level: the map patch at the true pose beside the camera frame (Small-v3, with
    the perspective camera for the relief level)."""
    from aerial_loc_env.pictures import write_realism_pictures

    levels = [("plain", "plain", "AerialLoc/Small-v3", {}, "middle"),
              ("relief", "relief", "AerialLoc/Small-v3", {"perspective": {"enabled": True}}, "relief")]
    written = write_realism_pictures(tmp_path, seed=0, levels=levels)
    assert [p.name for p in written] == ["gap_plain.png", "gap_relief.png"]
    for path in written:
        img = cv2.imread(str(path))
        assert img.shape[1] == 2 * 64 + 6 and img.shape[0] > 64 + 28   # two 64 px panels, a gap, headers
