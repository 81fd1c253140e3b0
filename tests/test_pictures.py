"""The pictures CLI (``pictures.py``) on a real-map crop: ``--gsd`` without a world file, ``--crs`` with one."""

from __future__ import annotations

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
