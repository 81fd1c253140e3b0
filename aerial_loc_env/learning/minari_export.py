"""Recorded episodes as Minari datasets: what offline-RL users load as they load D4RL's.

``export_episodes(env_id, agent, n)`` flies ``n`` episodes (seeds ``seed .. seed + n - 1``) of a scenario with an
agent (``agents/<name>.toml``) through the episode driver, recording every observation, action, reward and
info with Minari's ``DataCollector``, and writes the dataset ``aerial-loc/<scenario>-<agent>-v<N>``: the
scenario's short name in kebab case and the scenario id's version, so a scenario whose frames change (a new
id version) gives new datasets, never a silently different one under an old id. Then::

    import minari
    dataset = minari.load_dataset("aerial-loc/small-mcl-ncc-v3")   # MINARI_DATASETS_PATH=<--out> if given
    env = dataset.recover_environment()                           # gym.make of the recorded scenario

Infos are recorded with one structure at every step (Minari stores them as arrays): the ground truth
``true_pose``, ``time_s``, ``step``, the sun and shadows, the prior (``prior_mean_xy_m`` and ``prior_std_m``,
NaN for a uniform prior), the scored ``position_error_m`` and ``estimate_xy_m`` (NaN on the first frame, which
answers nothing), ``gimbal_roll_pitch_rad`` (zeros without jitter) and ``exposure_gain`` (1 without
auto-exposure). Images are stored losslessly unless ``jpeg=True``. An existing dataset is never overwritten:
its id is refused, naming its folder, before any episode runs. The dataset's metadata ``aerial_loc`` (JSON) holds
the resolved scenario, the agent's configuration, the seeds and the package version.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import math
import os
import re
import warnings
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np

from aerial_loc_env.config import parse_assignments
from aerial_loc_env.errors import ConfigError, require_extra

DATASET_NAMESPACE = "aerial-loc"
#: the info keys every recorded step has (``RecordedInfo``)
INFO_KEYS = ("true_pose", "time_s", "step", "shadow_fraction", "sun_azimuth_deg", "sun_elevation_deg",
             "shadow_strength", "prior_mean_xy_m", "prior_std_m", "position_error_m", "estimate_xy_m",
             "gimbal_roll_pitch_rad", "exposure_gain")
_ID_RE = re.compile(r"(?:(?P<namespace>[\w-]+(?:/[\w-]+)*)/)?(?P<name>[\w-]+?)-v(?P<version>\d+)")


def _minari() -> Any:
    minari = require_extra("minari", "data", "Exporting episodes as a Minari dataset")
    require_extra("jax", "data", "Minari's DataCollector (minari[create])")
    return minari


def _kebab(name: str) -> str:
    return re.sub(r"(?<=[a-z0-9])(?=[A-Z])", "-", name).lower()


def default_dataset_id(env_id: str, agent: str) -> str:
    """``aerial-loc/<scenario>-<agent>-v<N>`` for scenario ``AerialLoc/<Scenario>-v<N>`` and agent spec ``agent``."""
    m = re.fullmatch(r"[A-Za-z0-9_]+/(?P<name>[A-Za-z0-9_]+)-v(?P<version>\d+)", env_id)
    if not m:
        raise ConfigError(f"dataset export: --env {env_id!r} is not a scenario id like 'AerialLoc/Small-v3' "
                          "(`aerial-loc scenarios` lists them)")
    agent_name = re.sub(r"[^A-Za-z0-9-]+", "-", Path(agent).stem).strip("-").lower()
    return f"{DATASET_NAMESPACE}/{_kebab(m['name'])}-{agent_name}-v{m['version']}"


def check_dataset_id(dataset_id: str) -> str:
    """``dataset_id`` itself when Minari can name a dataset by it, with a version (``<namespace>/<name>-v<N>``)."""
    if not isinstance(dataset_id, str) or not _ID_RE.fullmatch(dataset_id):
        raise ConfigError(f"dataset export: --id {dataset_id!r} is not a versioned dataset id; write it as "
                          f"'{DATASET_NAMESPACE}/<name>-v<version>' (e.g. '{DATASET_NAMESPACE}/small-mcl-ncc-v3': "
                          "letters, digits, '-' and '_', then -v and a number)")
    return dataset_id


def datasets_root(root: str | Path | None = None) -> Path:
    """Where datasets live: ``root``, else ``MINARI_DATASETS_PATH``, else Minari's default ``~/.minari/datasets``."""
    if root is not None:
        return Path(root).expanduser()
    env = os.environ.get("MINARI_DATASETS_PATH")
    return Path(env).expanduser() if env else Path.home() / ".minari" / "datasets"


@contextlib.contextmanager
def _datasets_path(root: Path) -> Iterator[None]:
    """Minari reads its datasets folder from ``MINARI_DATASETS_PATH`` when it writes: set it for the export."""
    before = os.environ.get("MINARI_DATASETS_PATH")
    os.environ["MINARI_DATASETS_PATH"] = str(root)
    try:
        yield
    finally:
        if before is None:
            os.environ.pop("MINARI_DATASETS_PATH", None)
        else:
            os.environ["MINARI_DATASETS_PATH"] = before


class RecordedInfo(gym.Wrapper, gym.utils.RecordConstructorArgs):
    """The env's ``info`` with one structure at every step, numbers only (see the module doc): what Minari can
    store. Observations, actions and rewards pass through unchanged. It is part of the recorded env spec, so
    ``dataset.recover_environment()`` gives the same infos."""

    def __init__(self, env: gym.Env) -> None:
        gym.utils.RecordConstructorArgs.__init__(self)
        gym.Wrapper.__init__(self, env)

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        obs, info = self.env.reset(seed=seed, options=options)
        return obs, recorded_info(info)

    def step(self, action: Any):
        obs, reward, terminated, truncated, info = self.env.step(action)
        return obs, reward, terminated, truncated, recorded_info(info)


def recorded_info(info: Mapping[str, Any]) -> dict[str, np.ndarray]:
    """``info`` in the recorded structure (``INFO_KEYS``)."""
    prior = info.get("prior")
    gaussian = prior is not None and getattr(prior, "kind", None) == "gaussian"
    nan2 = np.full(2, np.nan)
    return {
        "true_pose": np.asarray(info["true_pose"], np.float64),
        "time_s": np.float64(info["time_s"]),
        "step": np.int64(info["step"]),
        "shadow_fraction": np.float64(info["shadow_fraction"]),
        "sun_azimuth_deg": np.float64(info["sun_azimuth_deg"]),
        "sun_elevation_deg": np.float64(info["sun_elevation_deg"]),
        "shadow_strength": np.float64(info["shadow_strength"]),
        "prior_mean_xy_m": np.asarray(prior.mean_xy_m, np.float64) if gaussian else nan2,
        "prior_std_m": np.float64(prior.std_xy_m if gaussian else math.nan),
        "position_error_m": np.float64(info.get("position_error_m", math.nan)),
        "estimate_xy_m": np.asarray(info.get("estimate_xy_m", nan2), np.float64),
        "gimbal_roll_pitch_rad": np.asarray(info.get("gimbal_roll_pitch_rad", np.zeros(2)), np.float64),
        "exposure_gain": np.float64(info.get("exposure_gain", 1.0)),
    }


@dataclass(frozen=True)
class ExportResult:
    dataset_id: str
    path: Path            # the dataset's folder
    episodes: int
    steps: int


def export_episodes(env_id: str, agent: str, n_episodes: int, *, dataset_id: str | None = None,
                    root: str | Path | None = None, seed: int = 0, overrides: Mapping[str, Any] | None = None,
                    jpeg: bool = False, agent_params: Mapping[str, Any] | None = None) -> ExportResult:
    """Fly ``n_episodes`` of ``env_id`` (with gym.make ``overrides``) with the agent spec ``agent`` and write them
    as the Minari dataset ``dataset_id`` (default ``default_dataset_id``) under ``root`` (see the module doc)."""
    import aerial_loc_env.env  # noqa: F401  (registers the scenarios)
    from aerial_loc_env.config import config_to_dict
    from aerial_loc_env.env import scenario_spec_dict
    from aerial_loc_env.estimators.episode import EpisodeDriver
    from aerial_loc_env.estimators.registry import make_agent
    from aerial_loc_env.version import __version__

    minari = _minari()
    if isinstance(n_episodes, bool) or not isinstance(n_episodes, int) or n_episodes < 1:
        raise ConfigError(f"dataset export: --episodes {n_episodes!r} must be a positive integer")
    if isinstance(seed, bool) or not isinstance(seed, int) or seed < 0:
        raise ConfigError(f"dataset export: --seed {seed!r} must be a non-negative integer")
    dataset_id = check_dataset_id(dataset_id or default_dataset_id(env_id, agent))
    folder = datasets_root(root)
    path = folder / dataset_id
    if path.exists():
        raise ConfigError(f"dataset export: dataset {dataset_id!r} already exists at {path}; it is never "
                          "overwritten: give another --id (e.g. a higher -v<N>) or another --out folder")
    overrides = dict(overrides or {})
    spec = scenario_spec_dict(env_id, **overrides)          # validates the scenario and its overrides
    runner = make_agent(agent, **dict(agent_params or {}))  # validates the agent
    params = getattr(runner, "params", None)
    provenance = {"scenario": spec, "scenario_id": env_id, "overrides": overrides, "agent": agent,
                  "agent_params": config_to_dict(params) if hasattr(params, "__dataclass_fields__") else {},
                  "seeds": [seed, seed + n_episodes - 1], "aerial_loc_env": __version__}
    steps = 0
    folder.mkdir(parents=True, exist_ok=True)
    with _datasets_path(folder):
        env = gym.make(env_id, **overrides)
        collector = minari.DataCollector(RecordedInfo(env), record_infos=True, jpeg_encoding=bool(jpeg))
        try:
            with EpisodeDriver(collector, [runner]) as driver:
                for k in range(n_episodes):
                    steps += sum(1 for record in driver.episode(seed + k) if not record.last)
            if path.exists():   # made by someone else while the episodes ran
                raise ConfigError(f"dataset export: dataset {dataset_id!r} appeared at {path} during the export; "
                                  "it is never overwritten: give another --id")
            with warnings.catch_warnings():   # no e-mail or code permalink to give: Minari warns about each
                warnings.filterwarnings("ignore", message=".*(author_email|code_permalink).*", category=UserWarning)
                dataset = collector.create_dataset(
                    dataset_id, eval_env=env.spec, algorithm_name=str(agent), author="aerial_loc_env",
                    description=f"{n_episodes} episodes of {env_id} flown by agent {agent} (aerial_loc_env "
                                f"{__version__}), seeds {seed}..{seed + n_episodes - 1}",
                    requirements=[f"aerial-loc-env=={__version__}"])
            dataset.storage.update_metadata({"aerial_loc": json.dumps(provenance, sort_keys=True, default=str)})
        finally:
            collector.close()
    return ExportResult(dataset_id, path, n_episodes, steps)


# ----------------------------------------------------------------------------------------------- CLI
def _set_items(items: Sequence[str]) -> dict[str, Any]:
    return parse_assignments(items, where="dataset export: --set", example="flight.duration_s=20")


def main(argv: list[str] | None = None) -> int:
    """``aerial-loc dataset export``: recorded episodes as a Minari dataset."""
    ap = argparse.ArgumentParser(prog="aerial-loc dataset", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = ap.add_subparsers(dest="command", required=True)
    ex = sub.add_parser("export", help="fly episodes with an agent and write them as a Minari dataset")
    ex.add_argument("--env", required=True, help="scenario id, e.g. AerialLoc/Small-v3")
    ex.add_argument("--agent", required=True, help="agent spec (agents/<name>.toml or a path), e.g. mcl-ncc")
    ex.add_argument("--episodes", type=int, required=True, help="how many episodes (seeds SEED .. SEED+N-1)")
    ex.add_argument("--seed", type=int, default=0, help="first episode seed (default 0)")
    ex.add_argument("--id", dest="dataset_id",
                    help=f"dataset id (default {DATASET_NAMESPACE}/<scenario>-<agent>-v<the scenario's version>)")
    ex.add_argument("--out", help="datasets folder (default MINARI_DATASETS_PATH, else ~/.minari/datasets); "
                                  "load with MINARI_DATASETS_PATH=<out>")
    ex.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                    help="a scenario override (JSON value), e.g. flight.duration_s=20")
    ex.add_argument("--jpeg", action="store_true", help="JPEG-encode the images (smaller, lossy)")
    args = ap.parse_args(argv)
    res = export_episodes(args.env, args.agent, args.episodes, dataset_id=args.dataset_id, root=args.out,
                          seed=args.seed, overrides=_set_items(args.set), jpeg=args.jpeg)
    print(f"dataset {res.dataset_id}: {res.episodes} episodes, {res.steps} steps -> {res.path}")
    hint = f"MINARI_DATASETS_PATH={datasets_root(args.out)} " if args.out else ""
    print(f"load it with: {hint}python -c \"import minari; print(minari.load_dataset('{res.dataset_id}'))\"")
    return 0
