"""Who may use the page (no rclpy, no web framework: unit-tested alone).

- Bound to a loopback address the page is this machine's, as ``lsu view`` is: no token.
- Bound to any other address every request and WebSocket needs the token: 32 random bytes from
  `secrets`, stored 0600 in the user's config folder, printed once when it is made. It travels in a
  cookie (HttpOnly, SameSite=Strict) set by ``/login`` or by a first ``?token=`` link, or in an
  ``Authorization: Bearer`` header (scripts), and is compared with `hmac.compare_digest` (constant time).
- Either way a request whose ``Origin`` is not the page's own is refused (no CORS: another site in the
  same browser must not drive the scanner), and the ``Host`` header must name this server (a DNS-rebinding
  page cannot reach a loopback-only server under its own name).
"""

from __future__ import annotations

import hmac
import os
import secrets
from dataclasses import dataclass
from pathlib import Path
from urllib.parse import urlsplit

LOOPBACK = ("127.0.0.1", "localhost", "::1")
COOKIE = "lsu_web_token"


def is_loopback(host: str) -> bool:
    return host in LOOPBACK or host.startswith("127.")


def token_file() -> Path:
    """Where the token lives: ``$XDG_CONFIG_HOME/lsu/web_token`` (default ``~/.config/lsu/web_token``)."""
    base = os.environ.get("XDG_CONFIG_HOME") or str(Path.home() / ".config")
    return Path(base) / "lsu" / "web_token"


def load_or_make_token(path: Path, renew: bool = False) -> tuple[str, bool]:
    """The stored token, or a new one written 0600 (then ``made`` is True and it is shown once).

    A token file readable by others is refused (it is a password): the user fixes it or renews.
    """
    if path.is_file() and not renew:
        mode = path.stat().st_mode & 0o777
        if mode & 0o077:
            raise PermissionError(f"{path} is readable by other users (mode {mode:o}); run 'chmod 600 {path}' or "
                                  f"start with --new-token")
        token = path.read_text().strip()
        if len(token) >= 32:
            return token, False
    token = secrets.token_urlsafe(32)
    path.parent.mkdir(parents=True, exist_ok=True, mode=0o700)
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    with os.fdopen(fd, "w") as f:
        f.write(token + "\n")
    os.chmod(path, 0o600)  # an existing file keeps its mode through O_CREAT
    return token, True


@dataclass(frozen=True)
class Access:
    """The server's rule: the token (None: loopback, no token) and the names this server answers to."""

    token: str | None
    hosts: frozenset[str]  # host names accepted in the Host header (any port: an SSH tunnel may forward another)

    def token_ok(self, offered: str | None) -> bool:
        if self.token is None:
            return True
        if not offered:
            return False
        return hmac.compare_digest(offered.encode(), self.token.encode())

    def host_ok(self, host_header: str | None) -> bool:
        if host_header is None:
            return False
        if self.token is not None:
            return True  # reached under any name (address, host name): the token guards it
        name = urlsplit("//" + host_header).hostname or ""
        return name in self.hosts

    def origin_ok(self, origin: str | None, host_header: str | None) -> bool:
        """No Origin (same-origin GET, scripts) or an Origin that is this very server."""
        if origin is None:
            return True
        parts = urlsplit(origin)
        return parts.scheme in ("http", "https") and parts.netloc == (host_header or "")


def access_for(host: str, token: str | None) -> Access:
    names = {host, "localhost", "127.0.0.1", "::1"} if is_loopback(host) else {host}
    return Access(token, frozenset(names))


def bearer(authorization: str | None) -> str | None:
    if authorization and authorization.lower().startswith("bearer "):
        return authorization[7:].strip()
    return None
