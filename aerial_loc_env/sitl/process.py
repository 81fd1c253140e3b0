"""The ArduPilot SITL process: find and check its binary, start it on loopback at the map, notice its death, kill it.

``SitlProcess`` starts an ArduPilot SITL binary (``../shared/sitl/`` by default) with SERIAL0 to the monitor and
SERIAL1 to the bridge, both UDP on 127.0.0.1 only; the process (its whole group) is always killed on exit, and
``check_alive`` turns its death into an error that says so, with its exit status and the end of its output.
"""

from __future__ import annotations

import os
import platform
import random
import shutil
import signal
import subprocess
import sys
import tempfile
from pathlib import Path

from aerial_loc_env.errors import AerialLocError, ConfigError
from aerial_loc_env.mavlink.cli import check_sim_speedup
from aerial_loc_env.mavlink.selfcheck import free_udp_port

# vehicle -> (binary, SITL's --model, ArduPilot's default parameter file)
VEHICLES = {"copter": ("arducopter", "+", "copter.parm"), "plane": ("arduplane", "plane", "plane.parm")}
DEFAULT_SITL_DIR = Path(__file__).resolve().parents[2].parent / "shared" / "sitl"
BUILD_HINT = "build ArduPilot SITL on this machine (./waf configure --board sitl && ./waf copter plane)"

# ELF e_machine of the architectures platform.machine() names (Linux), and how to say them
_ELF_MACHINE = {"x86_64": 62, "amd64": 62, "aarch64": 183, "arm64": 183, "i386": 3, "i686": 3, "armv7l": 40,
                "armv6l": 40, "riscv64": 243, "ppc64le": 21, "s390x": 22}
_ELF_NAMES = {62: "x86-64", 183: "ARM 64-bit (aarch64)", 3: "x86 32-bit", 40: "ARM 32-bit", 243: "RISC-V",
              21: "PowerPC 64", 22: "IBM s390x", 8: "MIPS"}


def check_program(path: Path, option: str = "--sitl-bin") -> None:
    """A regular file this machine can run: executable, and an ELF of this machine's architecture (Linux) or a
    ``#!`` script; else a clear error naming the file, the problem and the fix (the kernel's own answer is an
    'Exec format error' traceback)."""
    if not path.is_file():
        raise ConfigError(f"{option}: {path} is not a regular file; {BUILD_HINT} and give its folder")
    if not os.access(path, os.X_OK):
        raise ConfigError(f"{option}: {path} is not executable; make it so (chmod +x {path}) or {BUILD_HINT}")
    try:
        with open(path, "rb") as f:
            head = f.read(20)
    except OSError as exc:
        raise ConfigError(f"{option}: cannot read {path} ({exc.strerror}); give a SITL binary you may read") from exc
    if head.startswith(b"#!") or not sys.platform.startswith("linux"):
        return                                # a script, or another system's executable format: the OS decides
    if not head.startswith(b"\x7fELF") or len(head) < 20:
        raise ConfigError(f"{option}: {path} is not a program this machine can run (no ELF header, no #! line: a "
                          f"text file, an archive, a download that did not finish?); {BUILD_HINT}")
    order = "little" if head[5] == 1 else "big"
    e_type, e_machine = int.from_bytes(head[16:18], order), int.from_bytes(head[18:20], order)
    here = platform.machine()
    want = _ELF_MACHINE.get(here.lower())
    if want is not None and e_machine != want:
        built = _ELF_NAMES.get(e_machine, f"ELF machine {e_machine}")
        raise ConfigError(f"{option}: {path} is built for {built}, this machine is {here}; {BUILD_HINT}")
    if e_type not in (2, 3):                  # ET_EXEC, ET_DYN; not an object file or a core dump
        raise ConfigError(f"{option}: {path} is an ELF file but not a program (ELF type {e_type}: an object file "
                          f"or a core dump?); {BUILD_HINT}")


def find_sitl(vehicle: str, sitl_dir: str | os.PathLike | None = None) -> tuple[Path, Path, str]:
    """(binary, default parameter file, model) of ``vehicle`` in ``sitl_dir`` (default ../shared/sitl/), each
    checked: the binary a program this machine can run, the parameter file there."""
    if vehicle not in VEHICLES:
        raise ConfigError(f"--vehicle {vehicle!r}: use one of {', '.join(VEHICLES)}")
    exe, model, parm = VEHICLES[vehicle]
    folder = Path(sitl_dir) if sitl_dir is not None else DEFAULT_SITL_DIR
    if folder.is_file():
        raise ConfigError(f"--sitl-bin {folder}: is a file; give the folder that holds '{exe}' and '{parm}'")
    binary, defaults = folder / exe, folder / parm
    if not folder.is_dir():
        raise ConfigError(f"--sitl-bin {folder}: no such folder; {BUILD_HINT} and give its folder")
    if not binary.exists():
        raise ConfigError(f"--sitl-bin {folder}: no executable '{exe}' there; {BUILD_HINT} and give its folder")
    check_program(binary)
    if not defaults.is_file():
        raise ConfigError(f"--sitl-bin {folder}: no '{parm}' (ArduPilot's default parameters for {vehicle}, "
                          "Tools/autotest/ in its source)")
    return binary, defaults, model


def exit_status(returncode: int) -> str:
    """How a process ended, in words: 'exit code 3', 'killed by signal 9 (SIGKILL)'."""
    if returncode >= 0:
        return f"exit code {returncode}"
    try:
        name = signal.Signals(-returncode).name
    except ValueError:
        name = "unknown"
    return f"killed by signal {-returncode} ({name})"


def _die_with_parent() -> None:
    """In the child before exec: SIGKILL when the parent dies (Linux), so no SITL outlives a killed run."""
    try:
        import ctypes

        ctypes.CDLL(None, use_errno=True).prctl(1, signal.SIGKILL)    # PR_SET_PDEATHSIG
    except (OSError, AttributeError):
        pass


class SitlProcess:
    """One SITL instance on loopback (context manager; killed, with its process group, on exit)."""

    def __init__(self, vehicle: str, home: str, params: dict[str, float], *, speedup: float = 1.0,
                 sitl_dir: str | os.PathLike | None = None, scripts: tuple[Path, ...] = ()) -> None:
        self.binary, self.defaults, self.model = find_sitl(vehicle, sitl_dir)
        self.scripts = tuple(Path(p) for p in scripts)    # Lua scripts the autopilot runs (SCR_ENABLE 1)
        self.home, self.params, self.speedup = home, dict(params), check_sim_speedup(speedup, "--speedup")
        self.monitor_port, self.bridge_port = free_udp_port(), free_udp_port()
        self.instance = random.randint(20, 90)      # its other ports (RC in, sim) away from other instances
        self.workdir: Path | None = None
        self.proc: subprocess.Popen | None = None

    def __enter__(self) -> SitlProcess:
        self.workdir = Path(tempfile.mkdtemp(prefix="aerial_loc_sitl_"))
        extra = self.workdir / "extra.parm"
        extra.write_text("".join(f"{k} {v}\n" for k, v in self.params.items()))
        if self.scripts:                 # ArduPilot SITL runs the Lua scripts in ./scripts of its working folder
            (self.workdir / "scripts").mkdir()
            for script in self.scripts:
                shutil.copyfile(script, self.workdir / "scripts" / script.name)
        self.log = open(self.workdir / "sitl.log", "wb")   # noqa: SIM115 (closed in __exit__)
        # SITL binds ports of its own from its instance number (TCP 5760 + 10 I for the serial ports it serves,
        # UDP 5501 + 10 I for RC input) and exits at once when one is taken, e.g. by another SITL that drew the
        # same instance: draw again while it exits that way
        for attempt in range(6):
            start = (self.workdir / "sitl.log").stat().st_size
            cmd = [str(self.binary), "--model", self.model, "--speedup", f"{self.speedup:g}", "--home", self.home,
                   "--defaults", f"{self.defaults},{extra}", "--wipe", "-I", str(self.instance),
                   "--serial0", f"udpclient:127.0.0.1:{self.monitor_port}",
                   "--serial1", f"udpclient:127.0.0.1:{self.bridge_port}"]
            try:
                self.proc = subprocess.Popen(cmd, cwd=self.workdir, stdout=self.log, stderr=subprocess.STDOUT,
                                             start_new_session=True, preexec_fn=_die_with_parent)
            except OSError as exc:       # checked by find_sitl; changed since, or a loader missing
                self.__exit__()
                raise AerialLocError(f"SITL ({self.binary}) could not be started: {exc.strerror}; "
                                     f"{BUILD_HINT}") from exc
            try:
                self.proc.wait(1.0)          # a bind failure ends it within milliseconds
            except subprocess.TimeoutExpired:
                return self
            out = (self.workdir / "sitl.log").read_bytes()[start:].decode(errors="replace")    # this start's
            if "bind failed" not in out or attempt == 5:
                self.__exit__()
                raise AerialLocError(f"SITL ({self.binary.name}) exited at start ({exit_status(self.proc.returncode)})"
                                     f": {out[-600:]}")
            self.instance = random.randint(20, 90)
        return self

    def log_tail(self, lines: int = 12) -> str:
        """The last ``lines`` lines SITL wrote (stdout and stderr), '' before it started or after the exit."""
        path = self.workdir / "sitl.log" if self.workdir is not None else None
        if path is None or not path.is_file():
            return ""
        kept: list[list] = []          # [line, count]: a line SITL repeats is shown once, with its count
        for line in path.read_bytes()[-8000:].decode(errors="replace").strip().splitlines():
            if kept and kept[-1][0] == line:
                kept[-1][1] += 1
            else:
                kept.append([line, 1])
        return "\n".join(line if n == 1 else f"{line}  [{n} times]" for line, n in kept[-lines:])

    def check_alive(self) -> None:
        """Raise a clear error when SITL has ended (it should run until ``stop``): its exit status and the end of
        its output, at once, instead of a later timeout that names what it was waiting for."""
        code = self.proc.poll() if self.proc is not None else None
        if code is not None:
            tail = self.log_tail()
            raise AerialLocError(f"SITL ({self.binary.name}) died: {exit_status(code)}; the end of its output:\n"
                                 f"{tail or '(nothing)'}")

    def stop(self) -> None:
        """End SITL (its process group); idempotent. Its dataflash log stays until the context exits."""
        if self.proc is not None and self.proc.poll() is None:
            os.killpg(self.proc.pid, signal.SIGTERM)
            try:
                self.proc.wait(5)
            except subprocess.TimeoutExpired:
                os.killpg(self.proc.pid, signal.SIGKILL)
                self.proc.wait(5)

    @property
    def dataflash_log(self) -> Path | None:
        """The newest dataflash log SITL wrote (logs/NNNNNNNN.BIN in its working folder), None if none."""
        logs = sorted((self.workdir / "logs").glob("*.BIN")) if self.workdir is not None else []
        return logs[-1] if logs else None

    def __exit__(self, *exc: object) -> None:
        self.stop()
        self.log.close()
        if self.workdir is not None:
            shutil.rmtree(self.workdir, ignore_errors=True)
