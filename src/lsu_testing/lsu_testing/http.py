"""One HTTP request for the web page's tests: a JSON body in, the status and body out, an error status as an answer."""

from __future__ import annotations

import json
import urllib.error
import urllib.request
from typing import Any

__all__ = ["http"]


def http(url: str, method: str = "GET", body: Any = None, headers: dict[str, str] | None = None,
         timeout_s: float = 20.0) -> tuple[int, bytes]:
    """``method`` ``url`` with ``body`` as JSON (None: no body); returns (status, body) for errors too."""
    data = None if body is None else json.dumps(body).encode()
    req = urllib.request.Request(url, data=data, method=method,
                                 headers={"Content-Type": "application/json", **(headers or {})})
    try:
        with urllib.request.urlopen(req, timeout=timeout_s) as r:
            return r.status, r.read()
    except urllib.error.HTTPError as exc:
        return exc.code, exc.read()
