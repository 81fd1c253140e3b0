"""Resumable trial results: an append-only JSON-lines file is the source of truth.

Each finished trial is appended (and fsynced) at once, so an interrupted run loses nothing; a re-run skips
the trials whose key is already there. Rows already on disk are never rewritten or removed: the CSV/JSON
summaries are derived files regenerated from the JSON lines.

One run at a time per folder (``RunLock``: an exclusive lock on ``run.lock``, which holds the PID); the folder
belongs to the experiments named in ``experiment.json`` (``TrialStore.claim``), so another experiment's
results are never mixed in or have their report replaced unless asked.
"""

from __future__ import annotations

import csv
import hashlib
import json
import math
import os
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any

from aerial_loc_env.errors import ConfigError

TRIALS_FILE = "trials.jsonl"
FAILURES_FILE = "failures.jsonl"
LOCK_FILE = "run.lock"
MANIFEST_FILE = "experiment.json"
#: the files a run reads or writes in its folder (report.md and the summaries are replaced at the end)
RUN_FILES = (TRIALS_FILE, FAILURES_FILE, LOCK_FILE, MANIFEST_FILE, "trials.csv", "trials.json", "report.md")


def trial_key(agent: Mapping[str, Any], scenario: Mapping[str, Any], seed: int) -> str:
    """A stable key of (agent spec, scenario spec, seed): the same trial always gets the same key."""
    blob = json.dumps({"agent": agent, "scenario": scenario, "seed": int(seed)}, sort_keys=True, default=str)
    return hashlib.sha256(blob.encode()).hexdigest()[:20]


def finite_or_null(value: Any) -> Any:
    """``value`` (dicts, lists and tuples walked) with every non-finite float as None: JSON has no NaN."""
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if isinstance(value, dict):
        return {k: finite_or_null(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [finite_or_null(v) for v in value]
    return value


class TrialStore:
    """The results folder of one experiment run."""

    def __init__(self, out_dir: str | os.PathLike):
        self.out_dir = Path(out_dir)
        if self.out_dir.exists() and not self.out_dir.is_dir():
            raise ConfigError(f"results path '{self.out_dir}' exists and is not a folder; "
                              "choose another --out")
        self.out_dir.mkdir(parents=True, exist_ok=True)
        for name in RUN_FILES:    # checked before the run, not found when its last write fails
            path = self.out_dir / name
            if path.exists() and not path.is_file():
                raise ConfigError(f"results folder '{self.out_dir}': '{path}' is a folder (or not a regular "
                                  f"file) where the run keeps its {name}; move it out of the way, or choose "
                                  "another --out")
        self.path = self.out_dir / TRIALS_FILE
        self.failures_path = self.out_dir / FAILURES_FILE

    def rows(self) -> list[dict]:
        """All complete rows on disk, each trial once (the first row of a key: a file doubled by two runs at
        once, before the lock, counts each trial once). A torn last line from a killed run is ignored, and
        kept on disk. A line of valid JSON that is not a row (an object) is a ``ConfigError`` naming it: the
        file was edited or is not this package's, and guessing would mix foreign data into the results."""
        if not self.path.exists():
            return []
        out = []
        seen: set[str] = set()
        with open(self.path, "rb") as fh:
            for number, raw in enumerate(fh, start=1):
                line = raw.strip()
                if not line:
                    continue
                try:
                    row = json.loads(line)
                except (json.JSONDecodeError, UnicodeDecodeError):    # torn (or garbled) like a killed run's
                    continue
                if not isinstance(row, dict):
                    text = line.decode("utf-8", "replace")
                    shown = text if len(text) <= 60 else text[:57] + "..."
                    raise ConfigError(
                        f"{self.path}, line {number}: {shown} is not a trial row (each line is one JSON object "
                        f"written by a run); delete that line (the rows around it are kept), or choose another "
                        f"--out")
                key = row.get("key")
                if key is not None:
                    if key in seen:
                        continue
                    seen.add(key)
                out.append(row)
        return out

    def lock(self) -> RunLock:
        """The folder's run lock (use as a context manager)."""
        return RunLock(self.out_dir / LOCK_FILE)

    def claim(self, experiment: str, *, add: bool = False) -> None:
        """Record that ``experiment`` writes here; refuse a folder holding another experiment's results unless
        ``add`` (then both are named). A folder from before the manifest is judged by its report's title."""
        manifest = self.out_dir / MANIFEST_FILE
        names = self._owners(experiment, add)
        if experiment in names and manifest.exists():
            return
        from aerial_loc_env.paths import atomic_write_bytes

        names = names if experiment in names else [*names, experiment]
        atomic_write_bytes(manifest, json.dumps({"experiments": names}, indent=1).encode())

    def _owners(self, experiment: str, add: bool) -> list[str]:
        """The experiments the folder holds; refused when another's, unless ``add``."""
        manifest = self.out_dir / MANIFEST_FILE
        names = _manifest_names(manifest) if manifest.exists() else _report_title(self.out_dir / "report.md")
        if names and experiment not in names and not add:
            raise ConfigError(
                f"results folder '{self.out_dir}' holds the results of experiment "
                f"{', '.join(repr(n) for n in names)}, not {experiment!r}; choose another --out, or pass "
                f"--add (run_experiment(..., add=True)) to add {experiment!r}'s trials to it")
        return names

    def check(self, experiment: str, *, add: bool = False) -> None:
        """Everything ``claim`` and the run will refuse about this folder (its rows, its manifest, another
        experiment's results), found now, before any scenario is built or episode rendered; writes nothing."""
        self.rows()
        self._owners(experiment, add)

    def done_keys(self) -> set[str]:
        return {r["key"] for r in self.rows() if "key" in r}

    def append(self, row: Mapping[str, Any]) -> None:
        """Append one finished trial durably (one write of one line, then fsync)."""
        _append_line(self.path, row)

    def append_failure(self, record: Mapping[str, Any]) -> None:
        """Log an agent that raised (not a finished trial: a re-run tries it again)."""
        _append_line(self.failures_path, record)


def _manifest_names(manifest: Path) -> list[str]:
    """The experiments a manifest names: ``{"experiments": [names]}``; a single name written as a string
    counts as that one name (not as its letters)."""
    try:
        names = json.loads(manifest.read_text(encoding="utf-8"))["experiments"]
    except (OSError, ValueError, KeyError, TypeError, UnicodeDecodeError) as exc:
        raise ConfigError(f"{manifest}: not a results manifest ({type(exc).__name__}: {exc}); it should read "
                          '{"experiments": ["<name>", ...]}: fix it, or choose another --out') from exc
    if isinstance(names, str):
        names = [names]
    if not isinstance(names, list) or not all(isinstance(n, str) and n for n in names):
        raise ConfigError(f"{manifest}: \"experiments\" is {json.dumps(names)}, not a list of experiment names; "
                          'it should read {"experiments": ["<name>", ...]}: fix it, or choose another --out')
    return names


def _report_title(path: Path) -> list[str]:
    """The experiment a report.md written before the manifest belongs to (its '# title' line), if any."""
    try:
        first = path.read_text(encoding="utf-8").splitlines()[0]
    except (OSError, UnicodeDecodeError, IndexError):
        return []
    return [first[2:].strip()] if first.startswith("# ") else []


class RunLock:
    """One benchmark run at a time in a results folder.

    An exclusive ``flock`` on the lock file, which holds the owner's PID: the kernel drops the lock when the
    owner dies (even by SIGKILL), so a stale file of a dead run is simply taken over. Without ``fcntl``
    (Windows) the file is created exclusively and a file naming a dead PID is taken over.
    """

    def __init__(self, path: Path) -> None:
        self.path = Path(path)
        self._fd: int | None = None
        self._portable = False

    def _owner(self) -> str:
        try:
            text = self.path.read_text(encoding="utf-8").strip()
        except (OSError, UnicodeDecodeError):
            text = ""
        return text.split()[0] if text else "unknown"

    def _busy(self, pid: str) -> ConfigError:
        return ConfigError(f"results folder '{self.path.parent}' is in use by another benchmark run (PID {pid}; "
                           f"lock file {self.path}); wait for it to finish, or choose another --out")

    def acquire(self) -> None:
        try:
            import fcntl
        except ImportError:  # pragma: no cover (not POSIX)
            self._portable = True
            self._acquire_portable()
            return
        try:
            fd = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o666)
        except OSError as exc:
            raise ConfigError(f"results folder '{self.path.parent}': cannot open the lock file {self.path} "
                              f"({exc.strerror}); if it is a folder, move it out of the way, or choose another "
                              "--out") from None
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            os.close(fd)
            raise self._busy(self._owner()) from None
        os.ftruncate(fd, 0)
        os.write(fd, f"{os.getpid()}\n".encode())
        self._fd = fd

    def _acquire_portable(self) -> None:  # pragma: no cover (not POSIX)
        for _ in range(2):
            try:
                fd = os.open(self.path, os.O_RDWR | os.O_CREAT | os.O_EXCL, 0o666)
            except FileExistsError:
                pid = self._owner()
                if pid.isdigit() and _pid_alive(int(pid)):
                    raise self._busy(pid) from None
                self.path.unlink(missing_ok=True)    # a dead run's lock: take it over
                continue
            os.write(fd, f"{os.getpid()}\n".encode())
            self._fd = fd
            return
        raise self._busy(self._owner())

    def release(self) -> None:
        if self._fd is None:
            return
        fd, self._fd = self._fd, None
        os.ftruncate(fd, 0)      # with flock the file stays (unlinking a locked file races with a new locker)
        os.close(fd)
        if self._portable:  # pragma: no cover (not POSIX)
            self.path.unlink(missing_ok=True)

    def __enter__(self) -> RunLock:
        self.acquire()
        return self

    def __exit__(self, *exc_info: object) -> None:
        self.release()


def _pid_alive(pid: int) -> bool:  # pragma: no cover (the portable fallback)
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def _append_line(path: Path, record: Mapping[str, Any]) -> None:
    line = json.dumps(finite_or_null(dict(record)), sort_keys=True) + "\n"
    # A torn line left by a killed run must not glue onto the next row.
    needs_newline = path.exists() and path.stat().st_size > 0 and not _ends_with_newline(path)
    with open(path, "a", encoding="utf-8") as fh:
        fh.write(("\n" if needs_newline else "") + line)
        fh.flush()
        os.fsync(fh.fileno())


def _ends_with_newline(path: Path) -> bool:
    with open(path, "rb") as fh:
        fh.seek(-1, os.SEEK_END)
        return fh.read(1) == b"\n"


FLAT_COLUMNS = ["agent", "scenario", "seed", "rmse_m", "rmse_converged_m", "final_error_m", "mean_error_m",
                "p95_error_m", "max_error_m", "time_to_converge_s", "converged", "diverged",
                "step_time_median_ms", "step_time_p95_ms", "compute_time_total_s", "cpu_time_total_s",
                "episode_render_cpu_s", "shadow_pairs_normalized",
                "shadow_fraction_mean",
                "steps", "version", "key"]


def write_summaries(rows: Iterable[Mapping[str, Any]], out_dir: Path) -> tuple[Path, Path]:
    """Regenerate the derived trials.csv and trials.json from the rows (atomic replace)."""
    from aerial_loc_env.paths import atomic_write_bytes

    rows = list(rows)
    out_dir = Path(out_dir)
    json_path = out_dir / "trials.json"
    csv_path = out_dir / "trials.csv"
    atomic_write_bytes(json_path, json.dumps(rows, indent=1, sort_keys=True).encode())
    import io

    buf = io.StringIO()
    from aerial_loc_env.benchmark.episodes import DETECTOR_COLUMNS

    # a grid's optional columns only when its rows have them: the file of a grid without them stays the same
    columns = FLAT_COLUMNS + [c for c in DETECTOR_COLUMNS.values() if any(c in r for r in rows)]
    writer = csv.DictWriter(buf, fieldnames=columns + ["agent_spec", "scenario_spec"], extrasaction="ignore")
    writer.writeheader()
    for r in rows:
        flat = {k: r.get(k) for k in columns}
        flat["agent_spec"] = json.dumps(r.get("agent_spec"), sort_keys=True)
        flat["scenario_spec"] = json.dumps(r.get("scenario_spec"), sort_keys=True)
        writer.writerow(flat)
    atomic_write_bytes(csv_path, buf.getvalue().encode())
    return csv_path, json_path
