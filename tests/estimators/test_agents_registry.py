"""Agent specs and the registry: every spec builds; overrides, dotted paths, classes and entry points work; bad
specs are clear errors; the protocol's Estimate checks itself; dead reckoning integrates the odometry."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import pytest
from shared_helpers import LATIN1
from test_dense_models import briefing_standin, textured_map

from aerial_loc_env.config import rng
from aerial_loc_env.errors import ConfigError
from aerial_loc_env.estimators import registry
from aerial_loc_env.estimators.dead_reckoning import DeadReckoningAgent
from aerial_loc_env.estimators.mcl.agent import MCLAgent
from aerial_loc_env.estimators.protocol import Agent, Estimate, parse_observation
from aerial_loc_env.estimators.registry import load_spec


@dataclass(frozen=True)
class _EchoParams:
    offset_m: float = field(default=0.0, metadata=rng(-10.0, 10.0))


class EchoAgent(Agent):
    """A test agent: the prior mean plus an offset."""

    Params = _EchoParams

    def __init__(self, params: _EchoParams) -> None:
        self.params = params

    def reset(self, briefing, *, seed=None) -> Estimate:
        self.xy = briefing.prior.mean_xy_m
        return self.step({})

    def step(self, observation, info=None) -> Estimate:
        return Estimate(self.xy[0] + self.params.offset_m, self.xy[1])


def test_every_spec_builds_and_lists(capsys) -> None:
    names = registry.spec_names()
    for expected in ("mcl-shadow-aware", "mcl-conventional", "mcl-restoration", "dead-reckoning", "mcl-global"):
        assert expected in names
    for name in names:                  # every spec parses and names a resolvable Agent class
        spec = registry.load_spec(name)
        assert issubclass(registry.resolve_class(spec.class_ref, where=spec.where), Agent) and spec.description
        if name.startswith("mcl-") or name == "dead-reckoning":    # these need no trained artefacts: build them
            agent = registry.build_agent(spec)
            assert isinstance(agent, Agent) and agent.name == name
    assert registry.main([]) == 0
    out = capsys.readouterr().out
    assert "mcl-shadow-aware" in out and "dead-reckoning" in out
    assert registry.main(["mcl-shadow-aware"]) == 0
    assert "measurement_params" in capsys.readouterr().out


def test_oracle_spec_asks_for_ground_truth() -> None:
    assert registry.make_agent("mcl-shadow-aware-oracle").uses_ground_truth is True
    assert registry.make_agent("mcl-shadow-aware").uses_ground_truth is False


def test_overrides_merge_nested_tables() -> None:
    agent = registry.make_agent("mcl-shadow-aware", n_particles=123, measurement_params={"n_pairs": 20})
    assert isinstance(agent, MCLAgent)
    assert agent.params.n_particles == 123
    assert agent.params.measurement_params == {"n_pairs": 20, "channels": 3, "activation": "multiply"}
    assert agent.measurement.config.n_pairs == 20


def test_dotted_paths_classes_and_short_names() -> None:
    assert isinstance(registry.make_agent("DeadReckoningAgent"), DeadReckoningAgent)
    a = registry.make_agent(f"{__name__}:EchoAgent", offset_m=2.0)
    assert isinstance(a, EchoAgent) and a.params.offset_m == 2.0
    assert isinstance(registry.make_agent(EchoAgent), EchoAgent)


def test_entry_points(monkeypatch) -> None:
    class FakeEP:
        name, value = "echo", f"{__name__}:EchoAgent"

        def load(self):
            return EchoAgent

    monkeypatch.setattr(registry, "entry_points", lambda group: [FakeEP()] if group == registry.ENTRY_POINT_GROUP
                        else [])
    assert isinstance(registry.make_agent("echo", offset_m=1.0), EchoAgent)
    assert isinstance(registry.resolve_class("echo"), type)


@pytest.mark.parametrize("overrides, match", [
    ({"n_particles": 0}, "n_particles"),
    ({"n_partikles": 10}, "unknown key"),
    ({"resampling": "best"}, "resampling"),
    ({"measurement": "nope"}, "unknown measurement model"),
    ({"measurement_params": {"n_pairs": -3}}, "n_pairs"),
    ({"injection_alpha_slow": 0.5, "injection_alpha_fast": 0.1}, "injection_alpha_fast"),
])
def test_bad_parameters_are_clear_errors(overrides, match) -> None:
    with pytest.raises(ConfigError, match=match) as exc:
        registry.make_agent("mcl-shadow-aware", **overrides)
    assert "mcl-shadow-aware.toml" in str(exc.value)


def test_bad_spec_files_are_clear_errors(tmp_path) -> None:
    cases = {
        "noclass.toml": ('description = "x"\n', "missing 'class'"),
        "unknown.toml": ('class = "NoSuchAgent"\n', "unknown agent class"),
        "notagent.toml": ('class = "aerial_loc_env.config:build_config"\n', "not an Agent subclass"),
        "nomodule.toml": ('class = "no.such.module:Thing"\n', "cannot import module"),
        "extra.toml": ('class = "MCLAgent"\nflavour = 1\n', "unknown top-level key"),
        "broken.toml": ('class = "MCLAgent\n', "invalid TOML"),
        "params.toml": ('class = "DeadReckoningAgent"\n[params]\nx = 1\n', "takes no parameters"),
    }
    for fname, (text, match) in cases.items():
        path = tmp_path / fname
        path.write_text(text)
        with pytest.raises(ConfigError, match=match):
            registry.make_agent(str(path))
    with pytest.raises(ConfigError, match="known: "):
        registry.make_agent("mcl-no-such-spec")


def test_estimate_and_observation_checks() -> None:
    with pytest.raises(ValueError, match="finite"):
        Estimate(float("nan"), 0.0)
    with pytest.raises(ValueError, match="status"):
        Estimate(0.0, 0.0, status="fine")
    e = Estimate(1.0, 2.0, cov_xy_m2=np.diag([4.0, 9.0]))
    assert e.std_m == pytest.approx(3.0)
    with pytest.raises(ConfigError, match="missing key"):
        parse_observation({"image": np.zeros((4, 4, 3), np.uint8)})
    with pytest.raises(ConfigError, match="uint8"):
        parse_observation({"image": np.zeros((4, 4)), "odometry": np.zeros(3), "yaw": [0.0], "altitude": [1.0]})


def test_dead_reckoning_integrates_the_odometry() -> None:
    m = textured_map(100)
    br = briefing_standin(m, mean_xy_m=(10.0, 20.0), std_xy_m=5.0)
    dr = registry.make_agent("dead-reckoning")
    est = dr.reset(br, seed=0)
    assert (est.x_m, est.y_m) == (10.0, 20.0) and est.std_m == pytest.approx(5.0)
    img = np.zeros((4, 4, 3), np.uint8)
    yaw = 0.0
    for _ in range(41):                                  # 1 motionless + 40 steps of a 0.1 rad/s turn at 8 m/s
        obs = {"image": img, "odometry": np.array([8.0, 0.1, 0.0], np.float32), "yaw": np.array([yaw], np.float32),
               "altitude": np.array([100.0], np.float32)}
        est = dr.step(obs)
        yaw += 0.1 * br.dt_s
    # exact arc: radius v / omega = 80 m, swept angle 40 * 0.025 = 1 rad (float32 yaws: ~1e-6 rad)
    x = 10.0 + 80.0 * math.sin(1.0)
    y = 20.0 + 80.0 * (1 - math.cos(1.0))
    assert math.hypot(est.x_m - x, est.y_m - y) < 0.05
    assert est.status == "dead_reckoning" and est.std_m > 5.0


def test_non_utf8_agent_spec_is_a_clear_error(tmp_path):
    p = tmp_path / "latin.toml"
    p.write_bytes(LATIN1)
    with pytest.raises(ConfigError, match=r"latin\.toml.*UTF-8"):
        load_spec(p)
