"""The vectorized env (``env/vector.py``): ``gym.make_vec`` in the sync, async and vector_entry_point modes steps
and resets; the vector_entry_point env equals SyncVectorEnv bit for bit for the same seeds across episode ends
(every autoreset mode), with its sub-envs in a worker process and in this one; the env checkers pass on a sub-env
and Gymnasium's tools for vector envs on the vector env; bad arguments, a bad action in a worker and a dead worker
are clear errors."""

from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
import warnings
from dataclasses import dataclass
from pathlib import Path

import cloudpickle
import gymnasium as gym
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env, data_equivalence
from gymnasium.utils.env_match import check_environments_match
from gymnasium.utils.passive_env_checker import check_obs
from gymnasium.vector import AutoresetMode

import aerial_loc_env  # noqa: F401  (registers the scenarios)
from aerial_loc_env.env import InvalidActionError
from aerial_loc_env.env.vector import AerialLocVectorEnv, batch_infos
from aerial_loc_env.errors import AerialLocError, ConfigError

SID = "AerialLoc/Small-v3"
SHORT = {"duration_s": 2.0}   # 8 steps per episode: an episode boundary within a few steps
STEPS = 19                    # two episode ends and their autoresets


def _actions(num_envs: int, steps: int, seed: int = 3) -> list[np.ndarray]:
    rng = np.random.default_rng(seed)
    return [rng.uniform(-1.0, 1.0, (num_envs, 2)).astype(np.float32) for _ in range(steps)]


def _assert_same_run(a: gym.vector.VectorEnv, b: gym.vector.VectorEnv, seed: int, steps: int = STEPS) -> int:
    """Reset both with ``seed`` and step them with the same actions: every output equal, bit for bit. Returns how
    many episode ends were crossed."""
    out_a, out_b = a.reset(seed=seed), b.reset(seed=seed)
    assert all(data_equivalence(x, y, exact=True) for x, y in zip(out_a, out_b, strict=True))
    ends = 0
    for k, actions in enumerate(_actions(a.num_envs, steps)):
        out_a, out_b = a.step(actions), b.step(actions)
        for name, x, y in zip(("obs", "reward", "terminated", "truncated", "info"), out_a, out_b, strict=True):
            assert data_equivalence(x, y, exact=True), f"step {k}: {name} differs"
        ends += int(np.count_nonzero(out_a[2] | out_a[3]))
    return ends


@pytest.mark.parametrize("mode", ["sync", "async", "vector_entry_point"])
def test_make_vec_steps_and_resets_in_every_mode(mode: str) -> None:
    envs = gym.make_vec(SID, num_envs=2, vectorization_mode=mode, **SHORT)
    try:
        obs, _info = envs.reset(seed=0)
        assert envs.observation_space.contains(obs) and obs["image"].shape == (2, 64, 64, 3)
        ends = 0
        for actions in _actions(2, 10):
            obs, reward, terminated, truncated, _info = envs.step(actions)
            assert envs.observation_space.contains(obs) and reward.shape == (2,) and np.all(reward <= 0.0)
            ends += int(np.count_nonzero(terminated | truncated))
        assert ends == 2                      # both flew their 8 steps, then autoreset
        assert envs.metadata["autoreset_mode"] == AutoresetMode.NEXT_STEP
    finally:
        envs.close()


def test_vector_entry_point_is_the_default_mode_and_spreads_over_processes() -> None:
    envs = gym.make_vec(SID, num_envs=3, processes=2, **SHORT)
    try:
        assert isinstance(envs.unwrapped, AerialLocVectorEnv)
        assert envs.unwrapped.processes == 2 and len(envs.unwrapped.local_envs) == 1
        assert envs.spec.kwargs["vectorization_mode"] == "vector_entry_point"
    finally:
        envs.close()


@pytest.mark.parametrize("processes", [1, 2])
def test_vector_entry_point_equals_sync_bit_for_bit_across_episode_ends(processes: int) -> None:
    ours = gym.make_vec(SID, num_envs=3, vectorization_mode="vector_entry_point", processes=processes, **SHORT)
    sync = gym.make_vec(SID, num_envs=3, vectorization_mode="sync", **SHORT)
    try:
        assert ours.unwrapped.processes == processes
        assert _assert_same_run(ours, sync, seed=11) == 6
        assert _assert_same_run(ours, sync, seed=[5, 3, 9], steps=4) == 0     # a seed per sub-env, and again
    finally:
        ours.close()
        sync.close()


def test_same_step_autoreset_equals_sync_with_final_obs_and_info() -> None:
    ours = gym.make_vec(SID, num_envs=2, autoreset_mode="SameStep", processes=2, **SHORT)
    sync = gym.make_vec(SID, num_envs=2, vectorization_mode="sync",
                        vector_kwargs={"autoreset_mode": AutoresetMode.SAME_STEP}, **SHORT)
    try:
        assert ours.metadata["autoreset_mode"] == AutoresetMode.SAME_STEP
        assert _assert_same_run(ours, sync, seed=4, steps=9) == 2
        _obs, _r, _term, trunc, info = ours.step(_actions(2, 1)[0])
        assert not trunc.any() and "final_obs" not in info
    finally:
        ours.close()
        sync.close()


def test_disabled_autoreset_resets_by_mask_as_sync() -> None:
    ours = gym.make_vec(SID, num_envs=2, autoreset_mode=AutoresetMode.DISABLED, processes=2, **SHORT)
    sync = gym.make_vec(SID, num_envs=2, vectorization_mode="sync",
                        vector_kwargs={"autoreset_mode": AutoresetMode.DISABLED}, **SHORT)
    try:
        for envs in (ours, sync):
            envs.reset(seed=[1, 2])
        for actions in _actions(2, 8):
            out_a, out_b = ours.step(actions), sync.step(actions)
            assert all(data_equivalence(x, y, exact=True) for x, y in zip(out_a, out_b, strict=True))
        assert out_a[3].all()
        with pytest.raises(AerialLocError, match="DISABLED.*reset_mask"):
            ours.step(actions)
        mask = np.array([False, True])
        assert all(data_equivalence(x, y, exact=True) for x, y in zip(ours.reset(options={"reset_mask": mask}),
                                                          sync.reset(options={"reset_mask": mask}), strict=True))
    finally:
        ours.close()
        sync.close()


def test_checkers_pass_on_a_sub_env_and_gymnasiums_vector_tools_on_the_vector_env() -> None:
    sb3_checker = pytest.importorskip("stable_baselines3.common.env_checker")
    envs = gym.make_vec(SID, num_envs=2, processes=2, **SHORT)
    try:
        sub = envs.unwrapped.local_envs[0]
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            check_env(sub)
            sb3_checker.check_env(sub, warn=True)
            obs, _ = envs.reset(seed=0)
            check_obs(obs, envs.observation_space, "reset")
            obs, *_ = envs.step(envs.action_space.sample())
            check_obs(obs, envs.observation_space, "step")
        assert [str(w.message) for w in caught] == []
    finally:
        envs.close()
    # Gymnasium's check that two envs match (for vector envs it compares the flags of one sub-env)
    one, sync = gym.make_vec(SID, num_envs=1, **SHORT), gym.make_vec(SID, num_envs=1, vectorization_mode="sync",
                                                                     **SHORT)
    try:
        check_environments_match(one, sync, num_steps=12, seed=2)
    finally:
        one.close()
        sync.close()


def test_infos_batch_as_gymnasium_does() -> None:
    sync = gym.vector.SyncVectorEnv([lambda: gym.make(SID, **SHORT)] * 3)
    cases = [
        [{"a": 1.5, "b": np.arange(2)}, None, {"b": np.ones(2, np.float32), "c": "x"}],
        [{"n": 1}, {"n": 2.7}, {"flag": True, "n": np.float32(3.0)}],
        [{"obj": (1, 2)}, {"obj": None}, {}],
        # every sub-env with every key (the one-call path), and the values that keep it off that path
        [{"t": 0.5, "s": 3, "f": False, "p": np.arange(3.0), "q": np.float32(1.5), "o": "a"},
         {"t": 1.5, "s": 4, "f": True, "p": np.arange(3.0) + 1, "q": np.float32(2.5), "o": "b"},
         {"t": -2.0, "s": 5, "f": True, "p": np.zeros(3), "q": np.float32(-1.0), "o": None}],
        [{"m": 1, "a": np.zeros(3, np.float32), "b": np.zeros((2, 2))},
         {"m": 2.5, "a": np.ones(3), "b": np.ones(2)},
         {"m": True, "a": np.arange(3, dtype=np.int16), "b": 7.0}],
    ]
    for infos in cases:
        expected: dict = {}
        for i, info in enumerate(infos):
            if info is not None:
                expected = sync._add_info(expected, info, i)
        batched = batch_infos(3, infos)
        assert data_equivalence(batched, expected, exact=True) and list(batched) == list(expected)
    assert batch_infos(3, [{"nested": {"x": 1}}, None, None]) is None     # left to _add_info
    sync.close()


@dataclass(frozen=True)
class Frozen:
    """An info object that cannot change (unless it holds one that can)."""

    x: object


def test_infos_through_the_shared_records_batch_as_gymnasium_does() -> None:
    """A worker packs each info into the shared records (numbers) and its message (objects, only when changed, and
    every time for one that can change in place), the message pickled as the channel carries it; the caller's batch
    equals Gymnasium's ``_add_info``, key order included, across changing layouts, absent sub-envs and infos no
    record holds (sent whole)."""
    import pickle

    from aerial_loc_env.env import vector
    from aerial_loc_env.env.vector import _INFO_RECORD_BYTES, _LOCAL, _InfoRecords

    def sent(entry: object) -> object:
        return pickle.loads(pickle.dumps(entry, protocol=pickle.HIGHEST_PROTOCOL))

    sync = gym.vector.SyncVectorEnv([lambda: gym.make(SID, **SHORT)] * 3)
    shared = bytearray(3 * _INFO_RECORD_BYTES)
    worker, caller = _InfoRecords(shared, 3, remote=True), _InfoRecords(shared, 3, remote=False)
    frozen, mutable, holder = Frozen(1.0), [1, 2], Frozen([5])    # holder: frozen, but its list is not
    rounds = [
        [{"t": 0.5, "p": np.arange(4.0), "s": 3, "o": frozen}, None, {"t": 1.5, "p": np.ones(4), "s": 4, "o": frozen}],
        [{"t": 0.5, "p": np.arange(4.0), "s": 3, "o": frozen}, {"t": 2.5, "p": np.zeros(4), "s": 5, "o": mutable},
         {"t": 1.5, "p": np.ones(4), "s": 4, "o": frozen}],
        [{"t": 7.0, "s": 1, "o": Frozen(2.0)}, {"t": 8.0, "s": 2, "o": mutable}, {"t": 9.0, "s": 3, "o": frozen}],
        [{"t": 7.0, "s": 1, "o": holder}, {"t": 8.0, "s": 2, "o": mutable}, {"s": 3, "t": 9.0, "o": frozen}],
        [{"t": 7.0, "s": 1, "o": holder}, {"t": 8.0, "s": 2, "o": mutable}, {"s": 3, "t": 9.0, "o": frozen}],
        [{"f": True, "q": np.float32(1.5), "b": np.bool_(True)}, {"f": False, "q": np.float32(2.5), "b": None},
         {"big": np.zeros(_INFO_RECORD_BYTES)}],
        [{"nested": {"x": 1}}, None, {"_hidden": 1.0}],   # left to _add_info, as by batch_infos
    ]
    for k, infos in enumerate(rounds):
        if k == 4:
            mutable.append(3)                             # changed in place: the caller must see it
            holder.x.append(6)
        # sub-envs 0 and 1 in a worker, sub-env 2 in the caller's own block
        entries = [caller.unpack(0, i, sent(worker.pack(i, info))) for i, info in enumerate(infos[:2])]
        entries.append(caller.unpack(_LOCAL, 2, caller.pack(2, infos[2])))
        expected: dict = {}
        for i, info in enumerate(infos):
            if info is not None:
                expected = sync._add_info(expected, info, i)
        batched = caller.batched(3, entries, sync._add_info)
        assert data_equivalence(batched, expected, exact=True) and list(batched) == list(expected), f"round {k}"
    assert worker.pack(0, rounds[0][0])[2] == (("o", frozen),)                   # another object than last time
    packed = worker.pack(0, rounds[0][0])
    assert isinstance(packed, vector._Packed) and packed[1] is None and packed[2] == ()   # the object held already
    assert worker.pack(0, rounds[3][0])[2] == worker.pack(0, rounds[3][0])[2] == (("o", holder),)   # it may change
    assert worker.pack(1, rounds[1][1])[2] == (("o", mutable),)                  # a list: sent every time
    big = {"n": 2**70}
    assert worker.pack(0, big) is big                  # no int64 holds it: the info goes whole (as it was)
    many = [{f"key_{k}": 1.0} for k in range(vector._MAX_INFO_LAYOUTS + 1)]   # a new layout every time
    packed = [worker.pack(0, info) for info in many]
    assert len(worker._by_id) == vector._MAX_INFO_LAYOUTS and packed[-1] is many[-1]
    worker.forget()                                                               # (after a lost message)
    assert worker.pack(0, rounds[0][0])[1:] == ((("t", (float,)), ("p", ("array", "<f8", (4,))), ("s", (int,)),
                                                  ("o", ("object",))), (("o", frozen),))
    sync.close()


def test_a_steady_steps_answer_is_its_layout_ids_only() -> None:
    """A worker answers a step with its infos' layout ids alone (rewards and flags are in the shared outcomes) once
    the caller knows the layout and holds the objects; a new layout, an object to send or an info sent whole make it
    the full answer again."""
    from aerial_loc_env.env.vector import _INFO_RECORD_BYTES, _InfoRecords, _layout_ids

    worker = _InfoRecords(bytearray(2 * _INFO_RECORD_BYTES), 2, remote=True)
    frozen = Frozen(1.0)
    info = {"t": 0.5, "o": frozen}
    first = [worker.pack(0, info), worker.pack(1, dict(info))]
    assert _layout_ids(first) is None                       # the layout's signature goes with the first answer
    assert _layout_ids([worker.pack(0, info), worker.pack(1, dict(info))]) == (0, 0)
    assert _layout_ids([worker.pack(0, {"t": 1.5, "o": Frozen(2.0)}), worker.pack(1, info)]) is None  # a new object
    assert _layout_ids([worker.pack(0, {"t": 1.5, "o": [1]}), worker.pack(1, info)]) is None   # one that can change
    assert _layout_ids([worker.pack(0, {"n": 2**70}), worker.pack(1, info)]) is None           # an info sent whole
    assert _layout_ids([None, worker.pack(1, info)]) is None                                   # another op's result


def test_actions_of_another_dtype_go_as_given_and_big_infos_whole() -> None:
    """Float64 actions reach the sub-envs unrounded (not through the float32 shared actions), integer actions are
    refused as a single env refuses them, and an info too big for a record (the shadow mask) arrives whole: all
    equal to SyncVectorEnv."""
    kw = {**SHORT, "observation.info_shadow_mask": True}
    ours = gym.make_vec(SID, num_envs=2, processes=2, **kw)
    sync = gym.make_vec(SID, num_envs=2, vectorization_mode="sync", **kw)
    try:
        for envs in (ours, sync):
            envs.reset(seed=6)
        for actions in _actions(2, 9, seed=8):
            actions = actions.astype(np.float64) + 1e-9    # not a float32 value
            out_a, out_b = ours.step(actions), sync.step(actions)
            assert all(data_equivalence(x, y, exact=True) for x, y in zip(out_a, out_b, strict=True))
        assert out_a[4]["shadow_mask"].shape == (2, 64, 64)
        with pytest.raises(InvalidActionError, match="float array"):
            ours.step(np.zeros((2, 2), np.int64))
    finally:
        ours.close()
        sync.close()


@pytest.mark.parametrize("mode", ["vector_entry_point", "async"])
def test_sub_env_factories_pickle_without_maps(mode: str) -> None:
    """What travels to a worker is the id and the overrides (a few KB), never a map."""
    envs = gym.make_vec(SID, num_envs=2, vectorization_mode=mode, **SHORT)
    try:
        assert len(cloudpickle.dumps(envs.unwrapped.env_fns[0])) < 4096
    finally:
        envs.close()


@pytest.mark.parametrize("num_envs", [0, -1, "a", 2.5, True])
def test_bad_num_envs_is_a_clear_error(num_envs) -> None:
    with pytest.raises(ConfigError, match=r"num_envs=.* must be a positive integer"):
        gym.make_vec(SID, num_envs=num_envs)


@pytest.mark.parametrize("kwargs, words", [
    ({"processes": 0}, "processes=0 must be a positive integer"),
    ({"autoreset_mode": "sometimes"}, "autoreset_mode='sometimes' is not one of"),
    ({"start_method": "teleport"}, "start_method='teleport' is not available"),
    ({"altitude_m": -5.0}, "altitude_m"),
])
def test_bad_options_are_clear_errors_before_any_worker_starts(kwargs: dict, words: str) -> None:
    with pytest.raises(ConfigError, match=words):
        gym.make_vec(SID, num_envs=2, **kwargs)


def test_a_bad_action_in_a_worker_raises_the_sub_envs_error_and_the_env_goes_on() -> None:
    envs = gym.make_vec(SID, num_envs=2, processes=2, **SHORT)
    try:
        envs.reset(seed=0)
        with pytest.raises(InvalidActionError, match="NaN"):
            envs.step(np.array([[np.nan, 0.0], [0.0, 0.0]], np.float32))      # sub-env 0 lives in the worker
        with pytest.raises(AerialLocError, match="3 actions for 2 sub-envs"):
            envs.step(np.zeros((3, 2), np.float32))
        envs.reset(seed=0)
        envs.step(np.zeros((2, 2), np.float32))
    finally:
        envs.close()


def test_after_a_failed_block_the_worker_sends_its_layouts_and_objects_again() -> None:
    """Sub-env 1's bad action fails the worker's block after sub-env 0 had packed its info (a layout the caller
    never received): the worker forgets what it sent, so the steps after a reset equal SyncVectorEnv's."""
    ours = gym.make_vec(SID, num_envs=3, processes=2, **SHORT)        # the worker holds sub-envs 0 and 1
    sync = gym.make_vec(SID, num_envs=3, vectorization_mode="sync", **SHORT)
    try:
        ours.reset(seed=2)
        with pytest.raises(InvalidActionError, match="NaN"):
            ours.step(np.array([[0.0, 0.0], [np.nan, 0.0], [0.0, 0.0]], np.float32))
        assert _assert_same_run(ours, sync, seed=5, steps=10) == 3
    finally:
        ours.close()
        sync.close()


def test_after_an_interrupted_step_the_vector_env_says_so_and_closes() -> None:
    """Ctrl-C in the caller's own block leaves the worker's answer unread: the next call is a clear error, not a
    step that reads the old answer, and close still stops the worker."""
    envs = gym.make_vec(SID, num_envs=2, processes=2, **SHORT)
    try:
        envs.reset(seed=0)
        local = envs.unwrapped.local_envs[0]

        def interrupted(action: object) -> None:
            raise KeyboardInterrupt

        local.step = interrupted
        with pytest.raises(KeyboardInterrupt):
            envs.step(np.zeros((2, 2), np.float32))
        with pytest.raises(AerialLocError, match="interrupted .* close this vector env and make a new one"):
            envs.step(np.zeros((2, 2), np.float32))
    finally:
        envs.close()
    assert not envs.unwrapped._shards._procs[0].is_alive()


def test_a_dead_worker_is_a_clear_error() -> None:
    envs = gym.make_vec(SID, num_envs=2, processes=2, **SHORT)
    try:
        envs.reset(seed=0)
        worker = envs.unwrapped._shards._procs[0]
        os.kill(worker.pid, signal.SIGKILL)
        worker.join(timeout=10)
        with pytest.raises(AerialLocError, match=r"worker process 0 .* exited with code -9 \(killed"):
            envs.step(np.zeros((2, 2), np.float32))
    finally:
        envs.close()


def test_the_readmes_example_runs_as_written(tmp_path: Path) -> None:
    readme = (Path(__file__).resolve().parents[2] / "README.md").read_text(encoding="utf-8")
    section = readme.split("### Vectorized environments\n", 1)[1].split("\n#", 1)[0]
    code = re.findall(r"^```python\n(.*?)^```", section, flags=re.MULTILINE | re.DOTALL)
    assert len(code) == 1 and "gym.make_vec(" in code[0]
    (tmp_path / "example.py").write_text(code[0] + "print(type(envs).__name__, obs['image'].shape)\n")
    done = subprocess.run([sys.executable, "example.py"], cwd=tmp_path, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    assert done.stdout == "AerialLocVectorEnv (4, 64, 64, 3)\n"


def test_a_receiver_stops_spinning_after_two_spins_in_a_row_ran_out() -> None:
    """The channel's wait: a message that comes within the spin keeps spinning on; one late message (a sub-env's
    reset) changes nothing; two in a row make the next ``_SLEEP_AFTER_MISSES`` waits sleep at once (a machine
    busier than its cores), after which a spin is tried again. The messages arrive intact either way."""
    import multiprocessing as mp
    import threading

    from aerial_loc_env.env import vector

    channel = vector._Channel(mp.get_context("fork"), spin_s=0.001)

    def late(message: int) -> None:
        timer = threading.Timer(0.05, channel.send, args=(True, message))    # well past the 1 ms spin
        timer.start()
        assert channel.receive(True, lambda: True) == message
        timer.join()

    channel.send(True, 1)
    assert channel.receive(True, lambda: True) == 1 and channel._misses == 0
    late(2)
    assert channel._misses == 1 and channel._sleep_next == 0                  # one late answer: still spinning
    late(3)
    assert channel._sleep_next == vector._SLEEP_AFTER_MISSES                  # two in a row: sleep at once
    for k in range(vector._SLEEP_AFTER_MISSES):
        late(10 + k)
    assert channel._sleep_next == 0 and channel._misses == 2                  # slept through; no spin counted
    channel.send(True, 99)
    assert channel.receive(True, lambda: True) == 99 and channel._misses == 0  # an answer in time: reset
    channel.close()
