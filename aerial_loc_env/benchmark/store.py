"""Resumable trial results: an append-only JSON-lines file is the source of truth.

Each finished trial is appended (and fsynced) at once, so an interrupted run loses nothing; a re-run skips
the trials whose key is already there. Rows already on disk are never rewritten or removed: the CSV/JSON
summaries are derived files regenerated from the JSON lines.
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

from ..errors import ConfigError

TRIALS_FILE = "trials.jsonl"
FAILURES_FILE = "failures.jsonl"


def trial_key(agent: Mapping[str, Any], scenario: Mapping[str, Any], seed: int) -> str:
    """A stable key of (agent spec, scenario spec, seed): the same trial always gets the same key."""
    blob = json.dumps({"agent": agent, "scenario": scenario, "seed": int(seed)}, sort_keys=True, default=str)
    return hashlib.sha256(blob.encode()).hexdigest()[:20]


def _clean(value: Any) -> Any:
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if isinstance(value, dict):
        return {k: _clean(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_clean(v) for v in value]
    return value


class TrialStore:
    """The results folder of one experiment run."""

    def __init__(self, out_dir: str | os.PathLike):
        self.out_dir = Path(out_dir)
        if self.out_dir.exists() and not self.out_dir.is_dir():
            raise ConfigError(f"results path '{self.out_dir}' exists and is not a folder; "
                              "choose another --out")
        self.out_dir.mkdir(parents=True, exist_ok=True)
        self.path = self.out_dir / TRIALS_FILE
        self.failures_path = self.out_dir / FAILURES_FILE

    def rows(self) -> list[dict]:
        """All complete rows on disk (a torn last line from a killed run is ignored, and kept on disk)."""
        if not self.path.exists():
            return []
        out = []
        with open(self.path, encoding="utf-8") as fh:
            for line in fh:
                line = line.strip()
                if not line:
                    continue
                try:
                    out.append(json.loads(line))
                except json.JSONDecodeError:
                    continue
        return out

    def done_keys(self) -> set[str]:
        return {r["key"] for r in self.rows() if "key" in r}

    def append(self, row: Mapping[str, Any]) -> None:
        """Append one finished trial durably (one write of one line, then fsync)."""
        _append_line(self.path, row)

    def append_failure(self, record: Mapping[str, Any]) -> None:
        """Log an agent that raised (not a finished trial: a re-run tries it again)."""
        _append_line(self.failures_path, record)


def _append_line(path: Path, record: Mapping[str, Any]) -> None:
    line = json.dumps(_clean(dict(record)), sort_keys=True) + "\n"
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
    from ..paths import atomic_write_bytes

    rows = list(rows)
    out_dir = Path(out_dir)
    json_path = out_dir / "trials.json"
    csv_path = out_dir / "trials.csv"
    atomic_write_bytes(json_path, json.dumps(rows, indent=1, sort_keys=True).encode())
    import io

    buf = io.StringIO()
    writer = csv.DictWriter(buf, fieldnames=FLAT_COLUMNS + ["agent_spec", "scenario_spec"],
                            extrasaction="ignore")
    writer.writeheader()
    for r in rows:
        flat = {k: r.get(k) for k in FLAT_COLUMNS}
        flat["agent_spec"] = json.dumps(r.get("agent_spec"), sort_keys=True)
        flat["scenario_spec"] = json.dumps(r.get("scenario_spec"), sort_keys=True)
        writer.writerow(flat)
    atomic_write_bytes(csv_path, buf.getvalue().encode())
    return csv_path, json_path
