"""Vectorized ``AerialLocEnv``: N sub-envs stepped in lockstep, spread over this process and worker processes.

``gym.make_vec("AerialLoc/<Name>-v<N>", num_envs=N)`` (``vectorization_mode="vector_entry_point"``, the default
for these ids) builds an ``AerialLocVectorEnv``. Gymnasium's ``"sync"`` and ``"async"`` modes work too; this one
is faster on several cores (README, "Vectorized environments").

Why processes and not threads: the compiled kernels release the GIL, but a small scenario's step is mostly Python
bookkeeping (the pose, the photometry draws, the observation and info dicts) that holds it, so sub-envs stepped
in threads of one process take turns. ``EnvShards`` splits the N sub-envs into one contiguous block per process:
the calling process steps the last block itself while each worker steps its own, so the caller's core works
instead of waiting, and each worker gets one message per step for its whole block (not one per sub-env).
Observations travel through shared memory, and so do a Box space's actions and the infos' numbers and numeric
arrays (``_InfoRecords``: one record per sub-env, laid out by the info's keys and kinds; the objects in an info go
in the message, and an unchanging one only when it changed), and the rewards and flags (``_Outcomes``): a steady
step's answer is then the infos' layout ids alone; the rest goes as one small pickle per worker and step. The
caller batches the infos from the records (one copy per key), which is what brings the lockstep's fixed cost per
step below a small scenario's step.
Sub-envs in one process share one ``World`` (``world.scene``); workers open the same map files (the procedural
city's disk cache is memory-mapped, so its pages are shared), and each sub-env is built in its worker from the
scenario id and overrides: nothing map-sized is pickled.

Results are those of ``SyncVectorEnv`` over the same sub-envs, bit for bit: ``reset(seed=s)`` seeds sub-env
``i`` with ``s + i``; the autoreset modes (``metadata["autoreset_mode"]``, next-step by default, same-step,
disabled with ``reset(options={"reset_mask": ...})``) and the info dict (one array per key with its ``_key``
mask) are Gymnasium's. ``EnvShards`` also serves ``learning.vec_env`` (stable-baselines3's VecEnv API).
"""

from __future__ import annotations

import dataclasses
import multiprocessing as mp
import operator
import os
import pickle
import time
import traceback
from collections.abc import Callable, Sequence
from typing import Any, NamedTuple

import gymnasium as gym
import numpy as np
from gymnasium import spaces
from gymnasium.vector import AutoresetMode, VectorEnv
from gymnasium.vector.utils import CloudpickleWrapper, batch_space, create_shared_memory, iterate
from gymnasium.vector.utils import read_from_shared_memory as _views_of

from aerial_loc_env.errors import AerialLocError, ConfigError

#: how often (seconds) a wait on a worker checks that the worker is still alive
_POLL_S = 1.0


def usable_cores() -> int:
    """The cores this process may run on (its affinity where the OS reports it)."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # pragma: no cover - not on Linux
        return max(1, os.cpu_count() or 1)


def check_count(name: str, value: Any, where: str, example: str) -> int:
    """``value`` as a positive int, or a ConfigError naming ``name``, the value and an example."""
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 1:
        raise ConfigError(f"{where}: {name}={value!r} must be a positive integer ({example})")
    return int(value)


# ------------------------------------------------------------------------------------ what a sub-env does
def _leaves(space: spaces.Space, views: Any, path: tuple = ()) -> list[tuple[tuple, Any]]:
    """The batched shared-memory views of ``space``'s leaves (Dict and Tuple spaces walked once), each with the
    keys that lead from an observation to its value: what one sub-env's observation is written through."""
    if isinstance(space, spaces.Dict):
        return [leaf for key, sub in space.spaces.items() for leaf in _leaves(sub, views[key], (*path, key))]
    if isinstance(space, spaces.Tuple):
        return [leaf for k, (sub, view) in enumerate(zip(space.spaces, views, strict=True))
                for leaf in _leaves(sub, view, (*path, k))]
    return [(path, views)]


def _put(leaves: list[tuple[tuple, Any]], slot: int, value: Any) -> None:
    """Write one sub-env's observation into slot ``slot`` of the batched views (``_leaves``)."""
    for path, view in leaves:
        item = value
        for key in path:
            item = item[key]
        view[slot] = item


# ------------------------------------------------------------------------------- infos through shared memory
#: bytes of shared record per sub-env for its info's numbers and numeric arrays; an info whose numbers need more
#: (a shadow mask in the info) travels pickled, as do infos that ``batch_infos`` leaves to ``_add_info``
_INFO_RECORD_BYTES = 1024
#: the most info layouts a process keeps; an info of a new layout beyond them travels pickled (an env whose info
#: keys change every step would otherwise grow the table without end)
_MAX_INFO_LAYOUTS = 64
_SCALAR_TYPES = (int, float, bool)
_IMMUTABLE_TYPES = (str, bytes, int, float, bool, complex, type(None))


def _left_to_add_info(key: Any) -> bool:
    """Whether ``batch_infos`` leaves an info with ``key`` to ``_add_info`` (a key that is not a string, a ``_``
    mask-like key, a same-step final observation)."""
    return type(key) is not str or key.startswith("_") or key == "final_obs"


def _info_kind(value: Any) -> tuple | None:
    """How ``batch_infos`` batches ``value``: ``(type,)`` a number (an array of its own dtype), ``("array", dtype,
    shape)`` a numeric array (one more leading axis), ``("object",)`` anything else it keeps as an object; None
    for what makes it leave the info to ``_add_info`` (a dict) or what no record holds (an array of objects or
    strings, a subclassed array)."""
    kind = type(value)
    if kind in _SCALAR_TYPES or issubclass(kind, np.number):
        return (kind,)
    if kind is np.ndarray:
        return ("array", value.dtype.str, value.shape) if value.dtype.kind in "biufc" else None
    if isinstance(value, (dict, np.ndarray)):
        return None
    return ("object",)


def _unchanging(value: Any, depth: int = 0) -> bool:
    """Whether ``value`` cannot change in place (so a receiver may keep the copy it got): immutable builtins, and
    tuples and frozen dataclass instances made of such values (a frozen dataclass holding a list can change)."""
    if type(value) in _IMMUTABLE_TYPES:
        return True
    if depth >= 4:
        return False
    if type(value) is tuple:
        return all(_unchanging(v, depth + 1) for v in value)
    params = getattr(value, "__dataclass_params__", None)
    if params is None or isinstance(value, type) or not params.frozen:
        return False
    return all(_unchanging(getattr(value, f.name), depth + 1) for f in dataclasses.fields(value))


class _InfoLayout:
    """The shape of one kind of info dict (``signature``: its keys in order, each with its ``_info_kind``): its
    numbers and numeric arrays as fields of a record of ``_INFO_RECORD_BYTES`` per sub-env in the shared
    ``records`` (``fields``: one (num_envs, ...) view per such key), its objects beside (in the messages).
    ``fits`` is False where the numbers need more than a record."""

    def __init__(self, signature: tuple, records: np.ndarray) -> None:
        self.signature = signature
        names, formats, offsets, end = [], [], [], 0
        for key, kind in signature:
            if kind[0] == "object":
                continue
            dtype = np.dtype(kind[0]) if len(kind) == 1 else np.dtype((np.dtype(kind[1]), kind[2]))
            start = -(-end // 8) * 8
            names.append(key)
            formats.append(dtype)
            offsets.append(start)
            end = start + dtype.itemsize
        self.fits = end <= _INFO_RECORD_BYTES
        self.fields: dict[str, np.ndarray] = {}
        if self.fits:
            self.rec = records.view(np.dtype({"names": names, "formats": formats, "offsets": offsets,
                                              "itemsize": _INFO_RECORD_BYTES}))
            self.fields = {name: self.rec[name] for name in names}
        # per key: its field (None for an object), the type of a number (None otherwise) and an array's dtype and
        # shape (None otherwise): what reading, batching and checking an info of this layout go by
        self.items = [(key, self.fields.get(key), kind[0] if len(kind) == 1 and kind[0] != "object" else None,
                       (np.dtype(kind[1]), kind[2]) if kind[0] == "array" else None) for key, kind in signature]
        self.object_keys = [key for key, kind in signature if kind[0] == "object"]
        self._numbers = operator.itemgetter(*names) if len(names) > 1 else (lambda info: (info[names[0]],)) \
            if names else (lambda info: ())

    def holds(self, info: dict) -> bool:
        """Whether ``info`` (whose keys are this layout's, in order) is of this layout."""
        for key, _, scalar, array in self.items:
            value = info[key]
            kind = type(value)
            if scalar is not None:
                if kind is not scalar:
                    return False
            elif array is not None:
                if kind is not np.ndarray or value.dtype != array[0] or value.shape != array[1]:
                    return False
            elif kind in _SCALAR_TYPES or isinstance(value, (np.ndarray, np.number, dict)):   # no object now
                return False
        return True

    def write(self, slot: int, info: dict) -> None:
        self.rec[slot] = self._numbers(info)

    def read(self, slot: int, objects: dict) -> dict:
        """Sub-env ``slot``'s info as it was written (numbers of their own Python or NumPy type, array copies)."""
        out: dict[str, Any] = {}
        for key, field, scalar, _ in self.items:
            if field is None:
                out[key] = objects[key]
            elif scalar is None:
                out[key] = np.array(field[slot])      # (a copy; a 0-d array stays an array)
            else:
                value = field[slot]
                out[key] = scalar(value) if scalar in _SCALAR_TYPES else value[()]
        return out

    def batch(self, present: list[bool], objects: Sequence[dict | None]) -> dict[str, Any]:
        """``batch_infos`` of the sub-envs ``present`` (one bool per sub-env), every one of this layout."""
        out: dict[str, Any] = {}
        mask = np.array(present)
        absent = None if all(present) else ~mask
        chosen = [i for i, here in enumerate(present) if here]
        for key, field, _, _ in self.items:
            if field is None:
                array = np.empty(len(present), dtype=object)     # (None where absent)
                for i in chosen:
                    array[i] = objects[i][key]
            else:
                array = field.copy()
                if absent is not None:
                    array[absent] = 0
            out[key] = array
            out[f"_{key}"] = mask.copy()
        return out


class _Packed(tuple):
    """An info in the shared records as a message carries it: (layout id, its signature the first time, the
    objects). Its own type, so that no info an env returns (a tuple, say) is taken for one."""

    __slots__ = ()


class _InRecord(NamedTuple):
    """The caller's side of a packed info: its layout and the sub-env whose record holds it."""

    layout: _InfoLayout
    slot: int


#: ``_InfoRecords.unpack``'s source for the caller's own sub-envs
_LOCAL = -1


class _InfoRecords:
    """The shared info records of all sub-envs, as one process sees them. ``pack`` writes a sub-env's info into its
    record and returns what goes in the message instead of the info: ``(layout id, its signature the first time a
    worker sends it, the objects)``, where a worker (``remote``) leaves out an object the caller holds already
    (the same unchanging value as last time); or the info itself where no record holds it. ``unpack`` (the
    caller's side) resolves an entry from a worker or from the caller's own sub-envs (``_LOCAL``)."""

    def __init__(self, buffer: Any, num_envs: int, remote: bool) -> None:
        self.records = np.frombuffer(buffer, dtype=np.uint8, count=num_envs * _INFO_RECORD_BYTES)
        self.remote = remote
        self._by_signature: dict[tuple, tuple[int, _InfoLayout]] = {}
        self._by_keys: dict[tuple, tuple[int, _InfoLayout]] = {}   # the last layout of each key sequence
        self._by_id: list[_InfoLayout] = []
        self._announced: set[int] = set()
        self._sent: dict[int, dict[str, Any]] = {}            # per sub-env: the objects the receiver holds
        self._remote: dict[int, dict[int, _InfoLayout]] = {}  # per process: its layout ids (the caller's side)
        self.objects: dict[int, dict[str, Any]] = {}          # per sub-env: its latest objects (the caller's side)

    def layout(self, signature: tuple) -> tuple[int, _InfoLayout]:
        found = self._by_signature.get(signature)
        if found is None:
            found = self._by_signature[signature] = (len(self._by_id), _InfoLayout(signature, self.records))
            self._by_id.append(found[1])
        return found

    def pack(self, slot: int, info: Any) -> Any:
        if type(info) is not dict:
            return info
        keys = tuple(info)
        found = self._by_keys.get(keys)
        if found is None or not found[1].holds(info):
            signature = []
            for key, value in info.items():
                kind = _info_kind(value)
                if kind is None or _left_to_add_info(key):
                    return info
                signature.append((key, kind))
            signature = tuple(signature)
            if signature not in self._by_signature and len(self._by_id) >= _MAX_INFO_LAYOUTS:
                return info
            found = self._by_keys[keys] = self.layout(signature)
        ident, layout = found
        if not layout.fits:
            return info
        try:
            layout.write(slot, info)
        except (OverflowError, ValueError, TypeError):     # a number its field cannot hold: sent whole
            return info
        if not self.remote:      # the caller's own sub-envs: nothing travels, every object is handed over
            return _Packed((ident, None, tuple((key, info[key]) for key in layout.object_keys)))
        sent = self._sent.setdefault(slot, {})
        objects = []
        for key in layout.object_keys:
            value = info[key]
            if not (key in sent and sent[key] is value):
                objects.append((key, value))
                if _unchanging(value):
                    sent[key] = value
                else:
                    sent.pop(key, None)
        new = ident not in self._announced
        self._announced.add(ident)
        return _Packed((ident, layout.signature if new else None, tuple(objects)))

    def forget(self) -> None:
        """After a message was lost (an error): announce every layout and send every object again."""
        self._announced.clear()
        self._sent.clear()

    def unpack(self, source: int, slot: int, entry: Any) -> Any:
        """``_InRecord`` for a packed entry from process ``source``, else the entry (None, an info sent whole)."""
        if type(entry) is not _Packed:
            return entry
        return self.resolve(source, slot, *entry)

    def resolve(self, source: int, slot: int, ident: int, signature: tuple | None, objects: tuple) -> _InRecord:
        """``unpack`` of a packed entry's parts (layout id, its signature where new, the objects sent)."""
        if source == _LOCAL:
            layout = self._by_id[ident]
        else:
            ids = self._remote.setdefault(source, {})
            if signature is not None:
                ids[ident] = self.layout(signature)[1]
            layout = ids[ident]
        self.objects.setdefault(slot, {}).update(objects)
        return _InRecord(layout, slot)

    def batch(self, num_envs: int, entries: Sequence[Any]) -> dict[str, Any] | None:
        """Gymnasium's batched info of the unpacked ``entries`` (one per sub-env: None, an info, an ``_InRecord``)
        where every present one is in a record of one layout (from the records); None otherwise (``dicts``)."""
        layout = None
        for entry in entries:
            if entry is None:
                continue
            if type(entry) is not _InRecord or (layout is not None and entry.layout is not layout):
                return None
            layout = entry.layout
        if layout is None:
            return {}
        return layout.batch([entry is not None for entry in entries], [self.objects.get(i) for i in range(num_envs)])

    def batched(self, num_envs: int, entries: Sequence[Any], add_info: Callable[[dict, dict, int], dict]
                ) -> dict[str, Any]:
        """Gymnasium's batched info of the unpacked ``entries``: from the records (``batch``), else from the infos
        read back (``dicts``) by ``batch_infos``, else one by one by ``add_info`` (``VectorEnv._add_info``)."""
        batched = self.batch(num_envs, entries)
        if batched is not None:
            return batched
        infos = self.dicts(entries)
        batched = batch_infos(num_envs, infos)
        if batched is None:
            batched = {}
            for i, info in enumerate(infos):
                if info is not None:
                    batched = add_info(batched, info, i)
        return batched

    def dicts(self, entries: Sequence[Any]) -> list[dict | None]:
        return [entry.layout.read(entry.slot, self.objects[entry.slot]) if type(entry) is _InRecord else entry
                for entry in entries]


class _Outcomes(NamedTuple):
    """The sub-envs' step outcomes in shared memory (one entry per sub-env): what ``step`` returns beside the
    observation and the info, written by the process that steps the sub-env and read by the caller as arrays, so
    that no message carries them. The dtypes are Gymnasium's batches (``SyncVectorEnv``'s rewards and flags)."""

    rewards: np.ndarray          # float64
    terminations: np.ndarray     # bool
    truncations: np.ndarray      # bool

    @classmethod
    def of(cls, buffer: Any, num_envs: int) -> _Outcomes:
        raw = np.frombuffer(buffer, dtype=np.uint8, count=num_envs * _OUTCOME_BYTES)
        return cls(raw[:8 * num_envs].view(np.float64), raw[8 * num_envs:9 * num_envs].view(np.bool_),
                   raw[9 * num_envs:].view(np.bool_))


#: bytes of shared outcome per sub-env (``_Outcomes``: a float64 reward and two bool flags)
_OUTCOME_BYTES = 10


class _Slot:
    """What an op sees of its sub-env's place in the batch: calling it with an observation writes that into the
    shared batch (the ``put`` of the ops' signature), ``action()`` copies the sub-env's row of the shared actions
    (the caller writes the next step's over it), ``pack(info)`` the info into the shared records (``_InfoRecords``),
    ``outcome(...)`` the step's reward and flags into the shared outcomes (``_Outcomes``)."""

    __slots__ = ("index", "_leaves", "_actions", "_records", "_outcomes")

    def __init__(self, index: int, leaves: list[tuple[tuple, Any]], actions: Any, records: _InfoRecords,
                 outcomes: _Outcomes) -> None:
        self.index, self._leaves, self._actions, self._records = index, leaves, actions, records
        self._outcomes = outcomes

    def __call__(self, obs: Any) -> None:
        _put(self._leaves, self.index, obs)

    def action(self) -> Any:
        return np.array(self._actions[self.index])

    def pack(self, info: Any) -> Any:
        return self._records.pack(self.index, info)

    def outcome(self, reward: Any, terminated: Any, truncated: Any) -> None:
        i, out = self.index, self._outcomes
        out.rewards[i] = reward
        out.terminations[i] = terminated
        out.truncations[i] = truncated


def _op_reset(env: gym.Env, put: Callable[[Any], None], seed: int | None, options: dict | None) -> dict:
    obs, info = env.reset(seed=seed, options=options)
    put(obs)
    return info


def _op_step(env: gym.Env, put: Callable[[Any], None], action: Any) -> tuple:
    obs, reward, terminated, truncated, info = env.step(action)
    put(obs)
    return reward, terminated, truncated, info


def _op_reset_packed(env: gym.Env, slot: _Slot, seed: int | None, options: dict | None) -> Any:
    """``reset``, its info in the shared records (``_InfoRecords.pack``), its outcome a next-step autoreset's (no
    reward, neither flag)."""
    obs, info = env.reset(seed=seed, options=options)
    slot(obs)
    slot.outcome(0.0, False, False)
    return slot.pack(info)


def _op_step_packed(env: gym.Env, slot: _Slot, *action: Any) -> Any:
    """``step`` with the given action or (none given) the sub-env's row of the shared actions; its reward and flags
    in the shared outcomes, its info in the shared records."""
    obs, reward, terminated, truncated, info = env.step(action[0] if action else slot.action())
    slot(obs)
    slot.outcome(reward, terminated, truncated)
    return slot.pack(info)


def _layout_ids(results: list) -> tuple[int, ...] | None:
    """The layout ids of a block's packed infos where that is all its answer holds (every result an info in the
    records whose layout the caller knows and whose objects it holds): the short answer of a step; else None."""
    ids = []
    for res in results:
        if type(res) is not _Packed or res[1] is not None or res[2]:
            return None
        ids.append(res[0])
    return tuple(ids)


def _op_step_same(env: gym.Env, put: Callable[[Any], None], action: Any) -> tuple:
    """Gymnasium's same-step autoreset: a finished episode's last observation and info go in the info."""
    obs, reward, terminated, truncated, info = env.step(action)
    final = None
    if terminated or truncated:
        final = {"final_obs": obs, "final_info": info}
        obs, info = env.reset()
    put(obs)
    return reward, terminated, truncated, info, final


def _op_call(env: gym.Env, put: Callable[[Any], None], name: str, args: tuple, kwargs: dict) -> Any:
    attr = env.get_wrapper_attr(name)
    return attr(*args, **kwargs) if callable(attr) else attr


def _op_set_attr(env: gym.Env, put: Callable[[Any], None], name: str, value: Any) -> None:
    env.set_wrapper_attr(name, value)


def _op_none(env: gym.Env, put: Callable[[Any], None]) -> None:
    return None


def _op_apply(env: gym.Env, put: Callable[[Any], None], fn: Callable[..., Any], *args: Any) -> Any:
    """``fn(env, put, *args)``: another API's step (``learning.vec_env``); ``fn`` is a module-level function."""
    return fn(env, put, *args)


_OPS: dict[str, Callable[..., Any]] = {"reset": _op_reset, "step": _op_step, "step_same": _op_step_same,
                                       "reset_packed": _op_reset_packed, "step_packed": _op_step_packed,
                                       "call": _op_call, "set_attr": _op_set_attr, "none": _op_none,
                                       "apply": _op_apply}


def _run_block(envs: Sequence[gym.Env], slots: Sequence[_Slot], commands: Sequence[tuple]) -> list:
    return [_OPS[op](env, slot, *args) for env, slot, (op, *args) in zip(envs, slots, commands, strict=True)]


class _RemoteError:
    """An exception raised in a worker, carried back with its traceback text (the exception itself when it
    pickles, as AerialLocError and the builtin errors do)."""

    def __init__(self, exc: BaseException, slot: int | None) -> None:
        self.text = "".join(traceback.format_exception(exc))
        self.slot = slot
        try:
            self.exc: BaseException | None = pickle.loads(pickle.dumps(exc))
        except Exception:
            self.exc = None

    def raise_it(self, worker: int) -> None:
        where = f"vector env worker {worker}" + (f", sub-env {self.slot}" if self.slot is not None else "")
        if self.exc is not None:
            self.exc.add_note(f"(raised in {where}; its traceback:\n{self.text.rstrip()})")
            raise self.exc
        raise AerialLocError(f"{where} failed:\n{self.text.rstrip()}")


#: how long (seconds) a process spins on a message's semaphore before it sleeps: in lockstep the answer comes
#: within about one block's step, and waking a sleeping process costs more (a system call and, in a VM, an
#: interrupt between cores); only where every process has a core of its own
_SPIN_S = 0.002
#: after two spins in a row ran out (the other process had no core: the machine is busier than its cores, or the
#: caller's own work between steps is long), the waits that sleep at once before a spin is tried again: spinning
#: then only took the core the answer needed (one spin that runs out, as while a sub-env resets, changes nothing)
_SLEEP_AFTER_MISSES = 64
#: bytes of shared buffer per direction and worker; a longer message (a big final observation, rendered frames)
#: goes through the pipe
_CAPACITY = 1 << 18
_IN_PIPE = 0xFFFFFFFF


class _Channel:
    """The messages between the caller and one worker, both ways: a message is pickled into a shared buffer (or
    the pipe, when it does not fit) and announced by a semaphore, on which the receiver spins for ``spin_s``
    before it sleeps (and, once two spins in a row have run out, sleeps at once for the next
    ``_SLEEP_AFTER_MISSES`` waits: on a machine busier than its cores the spinner held the core the answer
    needed). Requests and answers alternate, so each direction holds at most one message."""

    def __init__(self, ctx: Any, spin_s: float) -> None:
        self.sems = (ctx.Semaphore(0), ctx.Semaphore(0))            # to the worker, to the caller
        self.bufs = (ctx.RawArray("B", _CAPACITY), ctx.RawArray("B", _CAPACITY))
        self.pipe = ctx.Pipe()                                        # (the caller's end, the worker's end)
        self.spin_s = spin_s
        self._misses = 0              # spins in a row that ran out
        self._sleep_next = 0          # waits left that sleep at once (after two spins in a row ran out)
        self._views: tuple | None = None

    def __getstate__(self) -> dict:
        return {**self.__dict__, "_views": None}

    def _buf(self, k: int) -> memoryview:
        if self._views is None:
            self._views = tuple(memoryview(b).cast("B") for b in self.bufs)
        return self._views[k]

    def send(self, to_worker: bool, message: Any) -> None:
        data = pickle.dumps(message, protocol=pickle.HIGHEST_PROTOCOL)
        k = 0 if to_worker else 1
        buf = self._buf(k)
        if len(data) + 4 <= len(buf):
            buf[4:4 + len(data)] = data
            buf[:4] = len(data).to_bytes(4, "little")
            self.sems[k].release()
        else:        # announced first: the receiver drains the pipe while this writes
            buf[:4] = _IN_PIPE.to_bytes(4, "little")
            self.sems[k].release()
            self.pipe[k].send_bytes(data)

    def receive(self, in_worker: bool, alive: Callable[[], bool]) -> Any:
        """The next message; EOFError when ``alive()`` turns false while waiting."""
        k = 0 if in_worker else 1
        sem = self.sems[k]
        if sem.acquire(False):        # already there: the other process keeps up
            self._misses = 0
        else:
            spin_s = self.spin_s if self._sleep_next == 0 else 0.0
            self._sleep_next = max(0, self._sleep_next - 1)
            end = time.perf_counter() + spin_s
            while not sem.acquire(False):
                if time.perf_counter() >= end:
                    if spin_s > 0:
                        self._misses += 1
                        if self._misses >= 2:
                            self._sleep_next = _SLEEP_AFTER_MISSES
                    while not sem.acquire(timeout=_POLL_S):
                        if not alive():
                            raise EOFError
                    break
            else:
                if spin_s > 0:
                    self._misses = 0
        buf = self._buf(k)
        size = int.from_bytes(buf[:4], "little")
        return pickle.loads(self.pipe[1 - k].recv_bytes() if size == _IN_PIPE else bytes(buf[4:4 + size]))

    def close(self) -> None:
        for conn in self.pipe:
            conn.close()


def _worker(channel: _Channel, fns: CloudpickleWrapper, slots: list[int], shm: Any, num_envs: int,
            forked: bool, action_shm: Any, info_buffer: Any, outcome_buffer: Any) -> None:
    """A worker process: build the block's sub-envs, then run each step's commands until told to stop."""
    parent = mp.parent_process()
    alive = parent.is_alive if parent is not None else (lambda: True)
    envs: list[gym.Env] = []
    try:
        if not forked:   # the processes already spread over the cores (in a forked child this call hangs)
            import cv2

            cv2.setNumThreads(1)
        envs = [fn() for fn in fns.fn]
        space, action_space = envs[0].observation_space, envs[0].action_space
        leaves = _leaves(space, _views_of(space, shm, num_envs))
        actions = None if action_shm is None else _views_of(action_space, action_shm, num_envs)
        records = _InfoRecords(info_buffer, num_envs, remote=True)
        outcomes = _Outcomes.of(outcome_buffer, num_envs)
        places = [_Slot(i, leaves, actions, records, outcomes) for i in slots]
        channel.send(False, ("ok", (space, action_space)))
    except BaseException as exc:  # noqa: BLE001 - reported to the caller, which raises it
        channel.send(False, ("error", _RemoteError(exc, slots[len(envs)] if len(envs) < len(slots) else None)))
        return
    try:
        while True:
            commands = channel.receive(True, alive)
            if commands is None:
                break
            try:
                results = _run_block(envs, places, commands)
                ids = _layout_ids(results)
                channel.send(False, ("ok", results) if ids is None else ("ids", ids))
            except Exception as exc:  # noqa: BLE001 - reported to the caller, which raises it
                records.forget()     # the caller gets none of this block's entries
                channel.send(False, ("error", _RemoteError(exc, None)))
    except (EOFError, OSError, KeyboardInterrupt):
        pass
    finally:
        for env in envs:
            env.close()


def _start_method(requested: str | None, where: str) -> str:
    """``requested``, or multiprocessing's default (as Gymnasium's async mode: fork on Linux before Python 3.14,
    so workers inherit the loaded maps and compiled kernels and start at once)."""
    if requested is None:
        return mp.get_start_method()
    if requested not in mp.get_all_start_methods():
        raise ConfigError(f"{where}: start_method={requested!r} is not available here; use one of "
                          f"{mp.get_all_start_methods()} (or None for the default, {mp.get_start_method()!r})")
    return requested


class EnvShards:
    """The sub-envs of ``env_fns`` spread over ``processes`` processes (this one included) in contiguous blocks,
    run in lockstep by ``run``. The observations of all sub-envs sit in shared memory (``views``, batched as
    the observation space); ``run`` returns what each sub-env's command returned, in sub-env order.

    The block of this process is the last one and is built first, so that a bad configuration is reported here
    before any worker starts."""

    def __init__(self, env_fns: Sequence[Callable[[], gym.Env]], processes: int | None = None, *,
                 start_method: str | None = None, where: str = "vector env") -> None:
        self.num_envs = len(env_fns)
        if self.num_envs < 1:
            raise ConfigError(f"{where}: no sub-envs to run (num_envs must be a positive integer)")
        if processes is None:
            processes = usable_cores()
        processes = min(check_count("processes", processes, where, "1 runs every sub-env in this process"),
                        self.num_envs)
        blocks = [b.tolist() for b in np.array_split(np.arange(self.num_envs), processes)]
        self.local_slots: list[int] = blocks[-1]
        self.local_envs: list[gym.Env] = [env_fns[i]() for i in self.local_slots]
        self.observation_space = self.local_envs[0].observation_space
        self.action_space = self.local_envs[0].action_space
        self._where = where
        self._channels: list[_Channel] = []
        self._procs: list[Any] = []
        self._blocks = blocks[:-1]
        self.closed = False
        self._broken: str | None = None      # why the vector env cannot go on (a worker died)
        self.start_method = _start_method(start_method, where)
        ctx = mp.get_context(self.start_method)
        self._starting = True
        self._shm = create_shared_memory(self.observation_space, self.num_envs, ctx=ctx)
        self.views = _views_of(self.observation_space, self._shm, self.num_envs)
        self._leaves = _leaves(self.observation_space, self.views)
        # the actions of a Box action space and the infos' numbers also travel through shared memory (``step``
        # and ``reset`` of ``AerialLocVectorEnv``: the ops "step_packed" and "reset_packed")
        self._action_shm = create_shared_memory(self.action_space, self.num_envs, ctx=ctx) \
            if isinstance(self.action_space, spaces.Box) else None
        self.actions = None if self._action_shm is None else \
            _views_of(self.action_space, self._action_shm, self.num_envs)
        self._info_buffer = ctx.RawArray("B", self.num_envs * _INFO_RECORD_BYTES)
        self.info_records = _InfoRecords(self._info_buffer, self.num_envs, remote=False)
        self._outcome_buffer = ctx.RawArray("B", self.num_envs * _OUTCOME_BYTES)
        self.outcomes = _Outcomes.of(self._outcome_buffer, self.num_envs)
        self._local = [_Slot(i, self._leaves, self.actions, self.info_records, self.outcomes)
                       for i in self.local_slots]
        spin_s = _SPIN_S if processes <= usable_cores() else 0.0
        try:
            for slots in self._blocks:
                channel = _Channel(ctx, spin_s)
                fns = CloudpickleWrapper([env_fns[i] for i in slots])
                proc = ctx.Process(target=_worker, args=(channel, fns, slots, self._shm, self.num_envs,
                                                         self.start_method == "fork", self._action_shm,
                                                         self._info_buffer, self._outcome_buffer),
                                   daemon=True, name=f"aerial-loc vector worker {len(self._procs)}")
                self._channels.append(channel)
                proc.start()
                self._procs.append(proc)
            for k in range(len(self._procs)):
                obs_space, act_space = self._receive(k)
                if obs_space != self.observation_space or act_space != self.action_space:
                    raise ConfigError(f"{where}: the sub-envs of worker {k} have other spaces than the first "
                                      f"ones (observation {obs_space} vs {self.observation_space}); every "
                                      "sub-env must have the same spaces")
            self._starting = False
        except BaseException:
            self.close()
            raise

    @property
    def processes(self) -> int:
        """How many processes step the sub-envs (this one included)."""
        return len(self._procs) + 1

    def share_actions(self, actions: Any) -> bool:
        """Write ``actions`` into the shared actions if they are an array of their dtype and shape (each sub-env
        then reads its row: ``_Slot.action``); False (nothing written) for actions to send as they are."""
        shared = self.actions
        if shared is None or type(actions) is not np.ndarray or actions.dtype != shared.dtype \
                or actions.shape != shared.shape:
            return False
        shared[...] = actions
        return True

    def put(self, slot: int, obs: Any) -> None:
        """Write sub-env ``slot``'s observation into the shared batch."""
        _put(self._leaves, slot, obs)

    def run(self, commands: Sequence[tuple]) -> list:
        """One command per sub-env (``(op, *args)``, ops in ``_OPS``); the workers run theirs while this process
        runs its own block; returns the results in sub-env order. Every worker answers before an error is raised,
        so the next call starts clean. An interrupt (Ctrl-C) leaves answers unread and blocks half stepped: the
        vector env then refuses every further call with an error saying so (close it and make a new one)."""
        try:
            return self._run(commands)
        except (KeyboardInterrupt, SystemExit):
            self._broken = (f"{self._where}: a step was interrupted before every sub-env had answered; the sub-envs "
                            "and the messages are out of step: close this vector env and make a new one")
            raise

    def _run(self, commands: Sequence[tuple]) -> list:
        if self.closed:
            raise AerialLocError(f"{self._where}: the vector env is closed")
        if len(commands) != self.num_envs:
            raise AerialLocError(f"{self._where}: {len(commands)} commands for {self.num_envs} sub-envs")
        if self._broken is not None:
            raise AerialLocError(self._broken)
        for k, (channel, slots) in enumerate(zip(self._channels, self._blocks, strict=True)):
            try:
                channel.send(True, [commands[i] for i in slots])
            except OSError:          # a worker that died since the last call (a long message's pipe)
                self._procs[k].join(timeout=_POLL_S)
                self._broken = self._death(k)
                raise AerialLocError(self._broken) from None
        error: BaseException | None = None
        try:
            local = _run_block(self.local_envs, self._local, [commands[i] for i in self.local_slots])
        except Exception as exc:  # noqa: BLE001 - raised once the workers have answered
            error, local = exc, []
        results: list = [None] * self.num_envs
        remote_error: tuple[int, _RemoteError] | None = None
        for k, slots in enumerate(self._blocks):
            status, payload = self._receive_raw(k)
            if status == "error":
                remote_error = remote_error or (k, payload)
                continue
            if status == "ids":       # (a step's short answer: only the infos' layouts, ``_layout_ids``)
                for i, ident in zip(slots, payload, strict=True):
                    results[i] = self.info_records.resolve(k, i, ident, None, ())
                continue
            for i, res in zip(slots, payload, strict=True):   # (every answer unpacked: the records stay in step)
                results[i] = self._unpacked(k, i, commands[i][0], res)
        if remote_error is not None:
            remote_error[1].raise_it(remote_error[0])
        if error is not None:
            raise error
        for i, res in zip(self.local_slots, local, strict=True):
            results[i] = self._unpacked(_LOCAL, i, commands[i][0], res)
        return results

    def _unpacked(self, source: int, slot: int, op: str, result: Any) -> Any:
        """A packed op's info entry resolved (``_InfoRecords.unpack``); other results as they are."""
        if op == "step_packed" or op == "reset_packed":
            return self.info_records.unpack(source, slot, result)
        return result

    def _receive_raw(self, k: int) -> tuple[str, Any]:
        proc = self._procs[k]
        try:
            return self._channels[k].receive(False, proc.is_alive)
        except (EOFError, OSError):
            proc.join(timeout=_POLL_S)
            self._broken = self._death(k)
            raise AerialLocError(self._broken) from None

    def _death(self, k: int) -> str:
        proc = self._procs[k]
        what = f"{self._where}: worker process {k} (pid {proc.pid}) exited with code {proc.exitcode}"
        if not self._starting:
            return f"{what} (killed, or out of memory?); close this vector env and make a new one"
        if self.start_method != "fork":
            return (f"{what} while starting. With start_method {self.start_method!r} each worker imports the "
                    "main script again: put the script's code under `if __name__ == '__main__':` (Python's "
                    "multiprocessing guide, 'Safe importing of main module'), or use start_method='fork'; "
                    "the worker's own error is printed above")
        return f"{what} while starting; its error is printed above"

    def _receive(self, k: int) -> Any:
        status, payload = self._receive_raw(k)
        if status == "error":
            payload.raise_it(k)
        return payload

    def close(self) -> None:
        """Close the sub-envs here and in the workers, and stop the workers (idempotent)."""
        if self.closed:
            return
        self.closed = True
        for channel, proc in zip(self._channels, self._procs, strict=False):
            if proc.is_alive():
                try:
                    channel.send(True, None)
                except (OSError, ValueError):
                    pass
        for proc in self._procs:
            proc.join(timeout=5.0)
            if proc.is_alive():
                proc.terminate()
                proc.join(timeout=1.0)
        for channel in self._channels:
            channel.close()
        for env in getattr(self, "local_envs", []):
            env.close()


def batch_infos(num_envs: int, infos: Sequence[dict | None]) -> dict[str, Any] | None:
    """The sub-envs' infos (None: no info) as Gymnasium's ``VectorEnv._add_info`` batches them one after the
    other (one array per key, its dtype from the first sub-env that has the key, and the ``_key`` mask), in one
    pass per key. None where a value is a dict or a key starts with '_' (``_add_info``'s own path applies)."""
    present = [(i, info) for i, info in enumerate(infos) if info]
    order: dict[str, None] = {}
    for _, info in present:
        order.update(dict.fromkeys(info))
    out: dict[str, Any] = {}
    for key in order:
        pairs = [(i, info[key]) for i, info in present if key in info]
        first = pairs[0][1]
        kind = type(first)
        if _left_to_add_info(key):
            return None
        if kind in _SCALAR_TYPES or issubclass(kind, np.number):
            array = np.zeros(num_envs, dtype=kind)
        elif isinstance(first, np.ndarray):
            array = np.zeros((num_envs, *first.shape), dtype=first.dtype)
        else:
            array = np.full(num_envs, None, dtype=object)
        mask = np.zeros(num_envs, dtype=np.bool_)
        for i, value in pairs:
            if isinstance(value, dict):
                return None
            array[i] = value
            mask[i] = True
        out[key] = array
        out[f"_{key}"] = mask
    return out


def _copy(value: Any) -> Any:
    if isinstance(value, dict):
        return {k: _copy(v) for k, v in value.items()}
    if isinstance(value, tuple):
        return tuple(_copy(v) for v in value)
    return np.array(value, copy=True)


class _MakeEnv:
    """Builds one sub-env from the scenario id and overrides (pickled to workers: no maps inside); a registered
    id through ``gym.make`` (unwrapped), so that the sub-env has its spec as a single env has."""

    def __init__(self, scenario: Any, render_mode: str | None, overrides: dict) -> None:
        self.scenario, self.render_mode, self.overrides = scenario, render_mode, overrides

    def __call__(self) -> gym.Env:
        from aerial_loc_env.env.aerial_loc_env import AerialLocEnv

        if isinstance(self.scenario, str) and self.scenario in gym.registry:
            return gym.make(self.scenario, render_mode=self.render_mode, **self.overrides).unwrapped
        return AerialLocEnv(self.scenario, render_mode=self.render_mode, **self.overrides)


class AerialLocVectorEnv(VectorEnv):
    """``num_envs`` ``AerialLocEnv`` of one scenario as a Gymnasium ``VectorEnv`` (see the module doc).

    ``gym.make_vec(id, num_envs=N, **overrides)`` or ``AerialLocVectorEnv(N, scenario, **overrides)``; keyword
    options: ``processes`` (how many processes step the sub-envs, this one included; default: one per usable
    core, at most ``num_envs``; 1 keeps them all here), ``autoreset_mode`` (Gymnasium's ``AutoresetMode`` or its
    value, default next-step), ``copy`` (False returns views of the shared batch, overwritten by the next call),
    ``start_method`` (multiprocessing's; default its default, as Gymnasium's async mode).
    """

    def __init__(self, num_envs: int = 1, scenario: Any = "AerialLoc/Small-v3", render_mode: str | None = None, *,
                 processes: int | None = None, autoreset_mode: str | AutoresetMode = AutoresetMode.NEXT_STEP,
                 copy: bool = True, start_method: str | None = None, **overrides: Any) -> None:
        name = getattr(scenario, "id", scenario)
        where = f"make_vec({name!r})"
        num_envs = check_count("num_envs", num_envs, where, "the number of sub-envs, e.g. num_envs=4")
        try:
            self.autoreset_mode = AutoresetMode(autoreset_mode)
        except ValueError:
            raise ConfigError(f"{where}: autoreset_mode={autoreset_mode!r} is not one of "
                              f"{[m.value for m in AutoresetMode]}") from None
        self.num_envs = num_envs
        self.copy = bool(copy)
        self.env_fns = [_MakeEnv(scenario, render_mode, dict(overrides)) for _ in range(num_envs)]
        self._shards = EnvShards(self.env_fns, processes, start_method=start_method, where=where)
        first = self._shards.local_envs[0]
        self.metadata = {**first.metadata, "autoreset_mode": self.autoreset_mode}
        self.render_mode = first.render_mode
        self.single_observation_space = first.observation_space
        self.single_action_space = first.action_space
        self.observation_space = batch_space(self.single_observation_space, num_envs)
        self.action_space = batch_space(self.single_action_space, num_envs)
        self._rewards = np.zeros((num_envs,), dtype=np.float64)
        self._terminations = np.zeros((num_envs,), dtype=np.bool_)
        self._truncations = np.zeros((num_envs,), dtype=np.bool_)
        self._autoreset_envs = np.zeros((num_envs,), dtype=np.bool_)

    @property
    def processes(self) -> int:
        """How many processes step the sub-envs (this one included)."""
        return self._shards.processes

    @property
    def local_envs(self) -> list[gym.Env]:
        """The sub-envs that live in this process (the last block of sub-envs)."""
        return self._shards.local_envs

    def _observations(self) -> Any:
        return _copy(self._shards.views) if self.copy else self._shards.views

    def reset(self, *, seed: int | list[int | None] | None = None,
              options: dict[str, Any] | None = None) -> tuple[Any, dict[str, Any]]:
        """Reset the sub-envs (all, or those of ``options["reset_mask"]``); ``seed``: None, an int ``s`` (sub-env
        ``i`` gets ``s + i``) or one seed per sub-env."""
        n = self.num_envs
        if seed is None:
            seeds: list = [None] * n
        elif isinstance(seed, (int, np.integer)) and not isinstance(seed, bool):
            seeds = [seed + i for i in range(n)]
        else:
            seeds = list(seed)
            if len(seeds) != n:
                raise ValueError(f"If seeds are passed as a list the length must match num_envs={n} but got "
                                 f"length={len(seeds)}.")
        options = dict(options) if options is not None else None
        mask = np.ones(n, dtype=np.bool_)
        if options is not None and "reset_mask" in options:
            mask = options.pop("reset_mask")
            if not isinstance(mask, np.ndarray) or mask.shape != (n,) or mask.dtype != np.bool_ or not mask.any():
                raise ValueError(f"`options['reset_mask']` must be a numpy bool array of shape ({n},) with at "
                                 f"least one True value, got {mask!r}")
        results = self._shards.run([("reset_packed", seeds[i], options) if mask[i] else ("none",)
                                    for i in range(n)])
        self._terminations[mask] = False
        self._truncations[mask] = False
        self._autoreset_envs[mask] = False
        return self._observations(), self._infos([results[i] if mask[i] else None for i in range(n)])

    def _infos(self, entries: Sequence[Any]) -> dict[str, Any]:
        """The sub-envs' infos batched (``entries``: what ``EnvShards.run`` returned for each: None, an info, a
        packed info)."""
        return self._shards.info_records.batched(self.num_envs, entries, self._add_info)

    def step(self, actions: Any) -> tuple[Any, np.ndarray, np.ndarray, np.ndarray, dict[str, Any]]:
        """Step every sub-env with its row of ``actions``; finished sub-envs reset as ``autoreset_mode`` says."""
        mode = self.autoreset_mode
        if mode != AutoresetMode.SAME_STEP and self._shards.share_actions(actions):
            rows: list = [()] * self.num_envs
        else:
            rows = [(row,) for row in iterate(self.action_space, actions)]
            if len(rows) != self.num_envs:
                raise AerialLocError(f"step: {len(rows)} actions for {self.num_envs} sub-envs; pass one action "
                                     f"per sub-env (shape {self.action_space.shape})")
        if mode == AutoresetMode.NEXT_STEP:
            commands = [("reset_packed", None, None) if self._autoreset_envs[i] else ("step_packed", *rows[i])
                        for i in range(self.num_envs)]
        elif mode == AutoresetMode.DISABLED:
            if self._autoreset_envs.any():
                raise AerialLocError(f"step: sub-envs {np.flatnonzero(self._autoreset_envs).tolist()} finished "
                                     "their episodes; with autoreset_mode DISABLED reset them first "
                                     "(reset(options={'reset_mask': terminations | truncations}))")
            commands = [("step_packed", *row) for row in rows]
        else:
            commands = [("step_same", *row) for row in rows]
        results = self._shards.run(commands)
        if mode == AutoresetMode.SAME_STEP:
            step_infos: list[Any] = []
            finals: list[dict | None] = []
            for i, res in enumerate(results):
                self._rewards[i], self._terminations[i], self._truncations[i], info, final = res
                step_infos.append(info)
                finals.append(final)
        else:     # (the packed ops: rewards and flags in the shared outcomes, a reset's none and False)
            outcomes = self._shards.outcomes
            self._rewards[:] = outcomes.rewards
            self._terminations[:] = outcomes.terminations
            self._truncations[:] = outcomes.truncations
            step_infos, finals = results, []
        if any(f is not None for f in finals):   # Gymnasium's order: a sub-env's final info, then its info
            infos: dict[str, Any] = {}
            for i, info in enumerate(step_infos):
                if finals[i] is not None:
                    infos = self._add_info(infos, finals[i], i)
                infos = self._add_info(infos, info, i)
        else:
            infos = self._infos(step_infos)
        self._autoreset_envs = np.logical_or(self._terminations, self._truncations)
        return (self._observations(), np.copy(self._rewards), np.copy(self._terminations),
                np.copy(self._truncations), infos)

    def render(self) -> tuple[Any, ...]:
        """The sub-envs' frames (``render_mode="rgb_array"``), in sub-env order."""
        return self.call("render")

    def call(self, name: str, *args: Any, **kwargs: Any) -> tuple[Any, ...]:
        """Call method ``name`` of every sub-env (or read attribute ``name``); results in sub-env order."""
        return tuple(self._shards.run([("call", name, args, kwargs)] * self.num_envs))

    def get_attr(self, name: str) -> tuple[Any, ...]:
        """Attribute ``name`` of every sub-env."""
        return self.call(name)

    def set_attr(self, name: str, values: Any) -> None:
        """Set attribute ``name`` of every sub-env: one value for all, or a list/tuple of one per sub-env."""
        if not isinstance(values, (list, tuple)):
            values = [values] * self.num_envs
        if len(values) != self.num_envs:
            raise ValueError("Values must be a list or tuple with length equal to the number of environments. "
                             f"Got `{len(values)}` values for {self.num_envs} environments.")
        self._shards.run([("set_attr", name, v) for v in values])

    @property
    def np_random_seed(self) -> tuple[int, ...]:
        """The sub-envs' seeds."""
        return self.get_attr("np_random_seed")

    @property
    def np_random(self) -> tuple[np.random.Generator, ...]:
        """The sub-envs' random generators (copies, for those in workers)."""
        return self.get_attr("np_random")

    def close_extras(self, **kwargs: Any) -> None:
        if hasattr(self, "_shards"):
            self._shards.close()

    def __del__(self) -> None:
        if not getattr(self, "closed", True) and hasattr(self, "_shards"):
            self._shards.close()
