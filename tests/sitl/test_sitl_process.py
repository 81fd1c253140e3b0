"""The SITL process: its binary found and checked before anything starts, restarted when its ports are taken,
its death reported at once with its exit status and the end of its output."""

from __future__ import annotations

import math
import os
import platform
import signal
import time

import pytest

from aerial_loc_env.errors import AerialLocError, ConfigError
from aerial_loc_env.sitl.process import DEFAULT_SITL_DIR, SitlProcess, check_program, exit_status, find_sitl


def _wait_exit(sitl: SitlProcess) -> None:
    while sitl.proc.poll() is None:
        time.sleep(0.05)


def test_find_sitl_names_the_folder_the_binary_and_the_parameters(tmp_path, fake_sitl):
    assert DEFAULT_SITL_DIR.name == "sitl" and DEFAULT_SITL_DIR.parent.name == "shared"
    assert find_sitl("copter", fake_sitl) == (fake_sitl / "arducopter", fake_sitl / "copter.parm", "+")
    with pytest.raises(ConfigError, match="copter, plane"):
        find_sitl("rover", fake_sitl)
    with pytest.raises(ConfigError, match="no such folder"):
        find_sitl("copter", tmp_path / "absent")
    with pytest.raises(ConfigError, match="no executable 'arducopter'.*waf"):
        find_sitl("copter", tmp_path)
    with pytest.raises(ConfigError, match="is a file; give the folder that holds 'arducopter' and 'copter.parm'"):
        find_sitl("copter", fake_sitl / "arducopter")
    (fake_sitl / "plane.parm").unlink()
    with pytest.raises(ConfigError, match="no 'plane.parm'"):
        find_sitl("plane", fake_sitl)


def _elf_header(machine: int, e_type: int = 3) -> bytes:
    """The first 20 bytes of a little-endian 64-bit ELF file of ``machine`` and ``e_type``, then padding."""
    return (b"\x7fELF\x02\x01\x01" + bytes(9) + e_type.to_bytes(2, "little") + machine.to_bytes(2, "little")
            + bytes(200))


OTHER_MACHINE = 62 if platform.machine().lower() not in ("x86_64", "amd64") else 183     # x86-64 or aarch64
THIS_MACHINE = {"x86_64": 62, "amd64": 62, "aarch64": 183, "arm64": 183}.get(platform.machine().lower())


@pytest.mark.parametrize("case", ["not-executable", "text", "other-machine", "object-file", "folder"])
def test_sitl_bin_that_this_machine_cannot_run_is_refused_naming_the_problem(fake_sitl, case):
    """A binary the kernel would refuse ('Exec format error' traceback from Popen) is a clear error before
    anything starts: not executable, not a program, built for another machine, an ELF that is no program."""
    binary = fake_sitl / "arducopter"
    expected = {"not-executable": r"is not executable; make it so \(chmod \+x",
                "text": "is not a program this machine can run", "other-machine": "is built for .*this machine is",
                "object-file": "is an ELF file but not a program", "folder": "is not a regular file"}[case]
    if case == "not-executable":
        binary.chmod(0o644)
    elif case == "text":
        binary.write_text("just text\n")
    elif case == "other-machine":
        binary.write_bytes(_elf_header(OTHER_MACHINE))
    elif case == "object-file":
        if THIS_MACHINE is None:
            pytest.skip(f"no ELF machine number known here for {platform.machine()}")
        binary.write_bytes(_elf_header(THIS_MACHINE, e_type=1))
    else:
        binary.unlink()
        binary.mkdir()
    if case not in ("not-executable", "folder"):
        binary.chmod(0o755)
    with pytest.raises(ConfigError, match=expected):
        find_sitl("copter", fake_sitl)
    with pytest.raises(ConfigError, match=expected):
        SitlProcess("copter", "0,0,0,0", {}, sitl_dir=fake_sitl)
    assert not (fake_sitl / "runs").exists()


def test_sitl_bin_accepts_scripts_and_this_machines_programs(fake_sitl, real_sitl):
    check_program(fake_sitl / "arducopter")          # a '#!' script: the kernel runs it
    check_program(real_sitl("arducopter") / "arducopter")


@pytest.mark.parametrize("speedup", [-1.0, 0.0, math.nan, math.inf, 50.0])
def test_speedup_outside_the_range_is_refused_before_sitl_starts(fake_sitl, speedup):
    """SITL dies of a floating point exception at --speedup 0 or nan, and the bridge follows at most 20 x: the
    range is named before anything runs."""
    with pytest.raises(ConfigError, match=r"--speedup .*must be in \[0.1, 20\]"):
        SitlProcess("copter", "0,0,0,0", {}, speedup=speedup, sitl_dir=fake_sitl)
    assert not (fake_sitl / "runs").exists()


def test_sitl_drawing_a_taken_instance_starts_again_on_another(tmp_path):
    """SITL exits at once when its instance's ports are taken ("bind failed"): it is started again on another
    instance; any other early exit is a clear error with SITL's own words, and nothing is left behind."""
    (tmp_path / "copter.parm").write_text("")
    fake = tmp_path / "arducopter"
    # the first start finds its port taken; the next one runs
    fake.write_text(f"#!/bin/sh\nif [ ! -e {tmp_path}/taken ]; then touch {tmp_path}/taken; "
                    "echo 'bind failed on port 6532 - Address already in use'; exit 1; fi\nexec sleep 30\n")
    fake.chmod(0o755)
    sitl = SitlProcess("copter", "0,0,0,0", {}, sitl_dir=tmp_path)
    with sitl:
        assert sitl.proc.poll() is None and (tmp_path / "taken").exists()
        workdir = sitl.workdir
    assert sitl.proc.poll() is not None and not workdir.exists()
    # another exit, even after a start that found its port taken, is not retried
    (tmp_path / "taken").unlink()
    fake.write_text(f"#!/bin/sh\necho run >> {tmp_path}/runs\nif [ ! -e {tmp_path}/taken ]; then "
                    f"touch {tmp_path}/taken; echo 'bind failed on port 6532'; exit 1; fi\n"
                    "echo 'no such model'; exit 2\n")
    with pytest.raises(AerialLocError, match=r"exited at start \(exit code 2\).*no such model"):
        SitlProcess("copter", "0,0,0,0", {}, sitl_dir=tmp_path).__enter__()
    assert (tmp_path / "runs").read_text().count("run") == 2


def test_a_killed_sitl_is_reported_with_its_signal_and_its_output(fake_sitl):
    """SITL killed while it runs: check_alive says it died, by which signal, and what it wrote last (a wait
    would otherwise time out minutes later naming what it waited for)."""
    with SitlProcess("copter", "0,0,0,0", {}, sitl_dir=fake_sitl) as sitl:
        sitl.check_alive()                              # running: nothing to say
        os.kill(sitl.proc.pid, signal.SIGKILL)
        _wait_exit(sitl)
        with pytest.raises(AerialLocError, match=r"SITL \(arducopter\) died: killed by signal 9 \(SIGKILL\); the "
                                                 r"end of its output:\nSITL starting"):
            sitl.check_alive()


def test_a_sitl_that_exits_is_reported_with_its_exit_code(fake_sitl):
    (fake_sitl / "arducopter").write_text("#!/bin/sh\nsleep 1.5\necho 'PANIC: out of memory'\nexit 3\n")
    with SitlProcess("copter", "0,0,0,0", {}, sitl_dir=fake_sitl) as sitl:
        _wait_exit(sitl)
        with pytest.raises(AerialLocError, match=r"died: exit code 3; the end of its output:\nPANIC: out of memory"):
            sitl.check_alive()


def test_exit_status_and_log_tail_in_words(fake_sitl):
    assert exit_status(0) == "exit code 0" and exit_status(3) == "exit code 3"
    assert exit_status(-signal.SIGFPE) == "killed by signal 8 (SIGFPE)"
    sitl = SitlProcess("copter", "0,0,0,0", {}, sitl_dir=fake_sitl)
    assert sitl.log_tail() == ""                        # not started
    sitl.workdir = fake_sitl
    (fake_sitl / "sitl.log").write_text("start\n" + "Loaded defaults\n" * 12 + "bad\n")
    assert sitl.log_tail() == "start\nLoaded defaults  [12 times]\nbad"
    assert sitl.log_tail(lines=1) == "bad"


@pytest.mark.timeout(120)
def test_real_sitl_killed_in_flight_is_reported_at_once(real_sitl):
    """The real SITL, its monitor waiting on it as a mission does: killed, the wait ends with SITL's death (its
    signal and output), not with the wait's own timeout."""
    from aerial_loc_env.sitl.monitor import Monitor

    folder = real_sitl("arducopter")
    with SitlProcess("copter", "-35.363261,149.165230,584,0", {}, sitl_dir=folder) as sitl:
        monitor = Monitor(sitl.monitor_port, sitl.check_alive)
        try:
            monitor.start()
            os.kill(sitl.proc.pid, signal.SIGKILL)
            with pytest.raises(AerialLocError, match=r"SITL \(arducopter\) died: killed by signal 9 \(SIGKILL\)"):
                monitor.wait(lambda track: False, 3600.0, "the mission's last waypoint")
        finally:
            monitor.stop()
