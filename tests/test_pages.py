"""``pages.small_pages``: NumPy's huge-page request off inside, the setting before the outermost entry restored
after (nested, raised through, from several threads at once); the city and its epochs are drawn inside it."""

from __future__ import annotations

import threading

import pytest

from aerial_loc_env import pages
from aerial_loc_env.pages import small_pages

switch = pages._switch()
pytestmark = pytest.mark.skipif(switch is None, reason="this NumPy has no huge-page setting to switch")


def _state() -> bool:
    """NumPy's current huge-page request (set to a value and straight back)."""
    assert switch is not None
    previous = switch(True)
    switch(previous)
    return bool(previous)


@pytest.fixture(params=[True, False], ids=["huge pages requested", "not requested"])
def initial(request):
    """Each test runs from either setting; the setting the suite had comes back after it."""
    assert switch is not None
    before = switch(request.param)
    yield request.param
    switch(before)


def test_off_inside_and_restored_after(initial):
    with small_pages():
        assert _state() is False
    assert _state() is initial


def test_nested_entries_restore_at_the_outermost_exit(initial):
    with small_pages():
        with small_pages():
            assert _state() is False
        assert _state() is False        # the inner exit keeps it off
    assert _state() is initial


def test_restored_when_the_work_raises(initial):
    with pytest.raises(RuntimeError, match="inside"):
        with small_pages():
            raise RuntimeError("inside")
    assert _state() is initial


def test_overlapping_threads_restore_the_setting_before_the_first(initial):
    """Thread A enters, B enters, A leaves (B still inside: still off), B leaves: back to the setting before A."""
    a_in, b_in, a_out = threading.Event(), threading.Event(), threading.Event()
    seen: dict[str, bool] = {}

    def a() -> None:
        with small_pages():
            a_in.set()
            b_in.wait(10)
        a_out.set()

    def b() -> None:
        a_in.wait(10)
        with small_pages():
            b_in.set()
            a_out.wait(10)
            seen["b after a left"] = _state()

    threads = [threading.Thread(target=a), threading.Thread(target=b)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(20)
    assert seen == {"b after a left": False}
    assert _state() is initial


def test_the_city_is_drawn_in_small_pages(monkeypatch, initial):
    from aerial_loc_env.world.city import generator, small_city_config

    inside: list[bool] = []
    drawn = generator._generate

    def spy(cfg):
        inside.append(_state())
        return drawn(cfg)

    monkeypatch.setattr(generator, "_generate", spy)
    city = generator.generate_city(small_city_config(0, width_m=240.0, height_m=200.0))
    assert inside == [False] and city.rgb.shape[:2] == (800, 960)
    assert _state() is initial


def test_an_epoch_is_drawn_in_small_pages(monkeypatch, initial):
    from aerial_loc_env.config import build_config
    from aerial_loc_env.world.city import epochs, generator, small_city_config

    inside: list[bool] = []
    drawn = epochs._changed

    def spy(*args):
        inside.append(_state())
        return drawn(*args)

    monkeypatch.setattr(epochs, "_changed", spy)
    city = generator.generate_city(small_city_config(0, width_m=240.0, height_m=200.0))
    later = epochs.change_epoch(city, build_config(epochs.EpochConfig, {"grass_dryness": 0.5}, where="test"))
    assert inside == [False] and later.rgb.shape == city.rgb.shape
    assert _state() is initial
