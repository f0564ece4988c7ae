"""The ROS environment every LSU process runs in: localhost-only DDS and a chosen domain.

No rclpy import here: this module must run before rclpy is loaded, because the DDS settings
are read when the first context starts.
"""

from __future__ import annotations

import fcntl
import os
import pwd
from collections.abc import MutableMapping
from dataclasses import dataclass
from pathlib import Path
from typing import IO

from lsu_config import config_dir

DISCOVERY_VAR = "ROS_AUTOMATIC_DISCOVERY_RANGE"
DOMAIN_VAR = "ROS_DOMAIN_ID"
LOCALHOST = "LOCALHOST"
#: Domain used by the `lsu` command when the user chose none. 0 is the ROS default, so the
#: user's own robot software on this machine sees our topics without any setting.
DEFAULT_DOMAIN_ID = 0
#: Domains handed out to test sessions and demos; 0 stays free for interactive use.
CLAIMABLE_DOMAINS = range(1, 102)
_LOCK_DIR = Path(os.environ.get("LSU_DOMAIN_LOCK_DIR", "/tmp/lsu-ros-domains"))


@dataclass
class EnvReport:
    """What `apply_defaults` found and did, for `lsu doctor`."""

    discovery_range: str
    discovery_set_by_lsu: bool
    domain_id: str
    domain_set_by_lsu: bool


def apply_defaults(env: MutableMapping[str, str] | None = None) -> EnvReport:
    """Make DDS localhost-only and pick a domain, unless the user explicitly chose them.

    Modifies ``env`` (default: ``os.environ``) in place so child processes inherit it.
    """
    env = os.environ if env is None else env
    if not env.get("HOME") and not env.get("ROS_LOG_DIR"):
        # rcl's logging needs ~/.ros/log; from an empty environment (env -i, services) HOME is unset
        env["HOME"] = pwd.getpwuid(os.getuid()).pw_dir
    use_profiles(env)
    keep_large_buffers(env)
    set_range = not env.get(DISCOVERY_VAR)
    if set_range:
        env[DISCOVERY_VAR] = LOCALHOST
    set_domain = not env.get(DOMAIN_VAR)
    if set_domain:
        env[DOMAIN_VAR] = str(DEFAULT_DOMAIN_ID)
    return EnvReport(env[DISCOVERY_VAR], set_range, env[DOMAIN_VAR], set_domain)


def fastdds_profiles() -> Path:
    """The Fast DDS profile file of the LSU configuration."""
    return config_dir() / "dds" / "fastdds.xml"


_PROFILE_VARS = ("FASTRTPS_DEFAULT_PROFILES_FILE", "FASTDDS_DEFAULT_PROFILES_FILE")


def use_profiles(env: MutableMapping[str, str]) -> None:
    """Point Fast DDS at our profile file (short heartbeats: a lost image fragment is repaired in
    50 ms instead of 3 s), unless the user chose a file of their own."""
    profiles = fastdds_profiles()
    if profiles.is_file() and not any(env.get(v) for v in _PROFILE_VARS):
        for var in _PROFILE_VARS:
            env[var] = str(profiles)


#: glibc malloc tuning for processes that move camera frames (~1 MB each, several per snap).
#: With the defaults every frame a DDS reader hands over, and every one a publisher serializes,
#: comes from fresh pages (a new mapping, or heap top that was just given back to the kernel),
#: and the first touch of each page faults: taking a 640x480 frame cost 0.56-0.95 ms instead of
#: 0.33-0.41 ms in `lsu run replay` (measured 2026-11-30, 4 interleaved runs). Frame-sized blocks
#: are served from the heap and freed memory is kept for the next frame instead.
MALLOC_SETTINGS = {"MALLOC_MMAP_THRESHOLD_": 16 << 20, "MALLOC_TRIM_THRESHOLD_": 32 << 20}
_MALLOPT = {"MALLOC_TRIM_THRESHOLD_": -1, "MALLOC_MMAP_THRESHOLD_": -3}  # glibc's M_* parameter numbers


def keep_large_buffers(env: MutableMapping[str, str]) -> None:
    """Apply `MALLOC_SETTINGS` to ``env`` (for child processes) and, if it is ``os.environ``, to
    this process too (glibc reads the variables only at start-up); settings the user made stay."""
    for var, value in MALLOC_SETTINGS.items():
        if env.get(var):
            continue
        env[var] = str(value)
        if env is os.environ:
            try:
                import ctypes

                ctypes.CDLL(None).mallopt(_MALLOPT[var], value)
            except (OSError, AttributeError):  # not glibc: the variables still reach glibc children
                pass


class DomainClaim:
    """A ROS domain id held exclusively by this process (a lock file per id).

    Parallel test sessions and demos on one machine each claim a different id, so their
    graphs never see each other. The claim ends with `release()` or when the process exits.
    """

    def __init__(self, domain_id: int, handle: IO[str]) -> None:
        self.domain_id = domain_id
        self._handle: IO[str] | None = handle

    def release(self) -> None:
        """Give the domain back."""
        if self._handle is not None:
            self._handle.close()
            self._handle = None


def claim_domain(start_hint: int | None = None) -> DomainClaim:
    """Claim a free domain id from `CLAIMABLE_DOMAINS`.

    The search starts at a pid-dependent offset so concurrent claimers rarely race for the
    same lock file; the lock itself settles any race.
    """
    _LOCK_DIR.mkdir(parents=True, exist_ok=True)
    ids = list(CLAIMABLE_DOMAINS)
    offset = (os.getpid() if start_hint is None else start_hint) % len(ids)
    for domain_id in ids[offset:] + ids[:offset]:
        handle = open(_LOCK_DIR / f"{domain_id}.lock", "w")
        try:
            fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            handle.close()
            continue
        handle.write(str(os.getpid()))
        handle.flush()
        return DomainClaim(domain_id, handle)
    raise RuntimeError(
        f"all ROS domain ids {ids[0]}..{ids[-1]} are claimed by other LSU runs on this machine; "
        f"wait for them to end or set {DOMAIN_VAR} yourself"
    )


def isolate(env: MutableMapping[str, str] | None = None) -> DomainClaim:
    """Localhost-only DDS plus a freshly claimed domain (tests, demos)."""
    env = os.environ if env is None else env
    claim = claim_domain()
    use_profiles(env)
    keep_large_buffers(env)
    env[DISCOVERY_VAR] = LOCALHOST
    env[DOMAIN_VAR] = str(claim.domain_id)
    return claim
