"""The pictures CLI (``pictures.py``) on a real-map crop: ``--gsd`` without a world file, ``--crs`` with one."""

from __future__ import annotations

import pytest
from shared_helpers import crop_png


def test_pictures_take_crs_and_gsd(manila, tmp_path):
    from aerial_loc_env.pictures import main

    png, _lat, _lon = crop_png(manila, tmp_path, 1600)    # 155 m: room for the pictures' 42 m/s track
    rc = main(["--out", str(tmp_path / "a"), "--map", str(png), "--gsd", "0.097", "--altitude", "20",
               "--frames", "1"])
    assert rc == 0 and (tmp_path / "a" / "overview.png").is_file()
    t = manila.georef.pixel_to_crs
    v0 = u0 = (manila.width_px - 1600) // 2 + 200
    (tmp_path / "crop.pgw").write_text(f"{t[0]}\n0\n0\n{t[4]}\n{t[0] * u0 + t[2]}\n{t[4] * v0 + t[5]}\n")
    assert main(["--out", str(tmp_path / "b"), "--map", str(png), "--altitude", "20", "--frames", "1"]) == 2
    rc = main(["--out", str(tmp_path / "b"), "--map", str(png), "--crs", "EPSG:3395", "--altitude", "20",
               "--frames", "1"])
    assert rc == 0 and (tmp_path / "b" / "overview.png").is_file()


@pytest.mark.slow
def test_realism_pictures_fly_over_the_given_map(tmp_path, capsys):
    """``--realism --map FILE`` used to ignore the map and draw the procedural city: it now flies that map, with the
    kinds of gap that apply to it (no height model, no land cover: acquisition, camera, both) and names the others."""
    import cv2
    import numpy as np

    from aerial_loc_env.config import build_config
    from aerial_loc_env.pictures import main
    from aerial_loc_env.world.city import CityConfig, default_city

    city = default_city(build_config(CityConfig, {"seed": 5, "width_m": 400.0, "height_m": 400.0, "gsd_m": 0.5}))
    png = tmp_path / "plain.png"
    cv2.imwrite(str(png), np.ascontiguousarray(np.asarray(city.rgb)[..., ::-1]))
    rc = main(["--out", str(tmp_path / "out"), "--map", str(png), "--gsd", "0.5", "--altitude", "120", "--frames",
               "1", "--realism"])
    out, err = capsys.readouterr()
    assert rc == 0, err
    gaps = sorted(p.name for p in (tmp_path / "out").glob("gap_*.png"))
    assert gaps == ["gap_acquisition.png", "gap_camera.png", "gap_realistic.png"]
    assert "left out: epoch (needs the procedural city's land cover" in err and "relief and database_sun" in err
    picture = cv2.imread(str(tmp_path / "out" / "gap_camera.png"))
    assert picture.shape[1] == 2 * 600 + 6


def test_a_real_pair_picture_in_the_same_layout_as_the_simulated_gap(tmp_path, capsys):
    """``--realism --pair EARLIER LATER --pair-gsd G`` adds gap_real_pair.png, the pair flown as RealPair (map =
    the earlier image | camera over the later one) in the simulated levels' layout; --pair alone is refused."""
    import cv2
    from synthetic_pairs import write_pair

    from aerial_loc_env.pictures import main, pair_level, write_realism_pictures

    a, b = write_pair(tmp_path / "pair", size_px=1024, world_file=False)
    assert main(["--out", str(tmp_path / "x"), "--pair", str(a), str(b)]) == 2
    assert "give --realism too" in capsys.readouterr().err
    assert main(["--out", str(tmp_path / "x"), "--realism", "--pair-gsd", "0.5"]) == 2
    assert "give --pair too" in capsys.readouterr().err
    (path,) = write_realism_pictures(tmp_path / "out", levels=[], pair=(str(a), str(b), 0.5))
    assert path.name == "gap_real_pair.png" and pair_level(str(a), str(b))[2] == "AerialLoc/RealPair-v2"
    picture = cv2.imread(str(path))
    assert picture.shape[1] == 2 * 600 + 6
    half = picture.shape[1] // 2
    assert picture[60:, :half].std() > 5 and picture[60:, half + 6:].std() > 5      # both sides hold the ground


def test_readme_pictures_are_smaller_copies_of_the_pictures(tmp_path, capsys):
    """``write_readme_pictures``: each README picture from its source file, resized to its width (aspect kept) or
    kept, the ``.jpg`` ones JPEG-encoded; a missing source names itself; ``--readme-dir`` without ``--realism``
    (or with another map, or too few frames for frame 2) is refused before anything is drawn."""
    import cv2
    import numpy as np

    from aerial_loc_env.errors import ConfigError
    from aerial_loc_env.pictures import README_PICTURES, main, write_readme_pictures

    src = tmp_path / "pictures"
    src.mkdir()
    gen = np.random.default_rng(0)
    for _, made_from, _ in README_PICTURES:
        cv2.imwrite(str(src / made_from), gen.integers(0, 256, (300, 1800, 3), dtype=np.uint8))
    written = write_readme_pictures(src, tmp_path / "img")
    assert [p.name for p in written] == [name for name, _, _ in README_PICTURES]
    for (name, _, width), path in zip(README_PICTURES, written, strict=True):
        out = cv2.imread(str(path))
        assert out.shape == ((200, 1200, 3) if width == 1200 else (143, 860, 3) if width == 860 else (300, 1800, 3))
        assert path.read_bytes()[:3] == (b"\xff\xd8\xff" if name.endswith(".jpg") else b"\x89PN")
    (src / "gap_relief.png").unlink()
    with pytest.raises(ConfigError, match="gap_relief.png"):
        write_readme_pictures(src, tmp_path / "img2")
    for args in (["--readme-dir", "d"], ["--realism", "--frames", "2", "--readme-dir", "d"]):
        assert main(["--out", str(tmp_path / "o"), *args]) == 2
        assert "--readme-dir" in capsys.readouterr().err
    assert not (tmp_path / "o").exists() and not (tmp_path / "d").exists()


@pytest.mark.slow
def test_the_readmes_pictures_are_what_the_code_draws(tmp_path):
    """docs/img is current: ``make pictures``'s command redraws the README's pictures with the same pixels (the
    PNGs exactly; the JPEGs within a grey level, as another libjpeg build may encode them differently)."""
    from pathlib import Path

    import cv2
    import numpy as np

    from aerial_loc_env.pictures import README_PICTURES, main

    docs = Path(__file__).resolve().parents[1] / "docs" / "img"
    assert main(["--out", str(tmp_path / "all"), "--realism", "--readme-dir", str(tmp_path / "img")]) == 0
    for name, _, _ in README_PICTURES:
        drawn, kept = (cv2.imread(str(d / name)).astype(np.int16) for d in (tmp_path / "img", docs))
        assert drawn.shape == kept.shape, name
        if name.endswith(".png"):
            assert np.array_equal(drawn, kept), f"{name}: run `make pictures` and commit docs/img"
        else:
            assert np.abs(drawn - kept).mean() < 1.0, f"{name}: run `make pictures` and commit docs/img"
