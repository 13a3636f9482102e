"""Request validation errors as JSON-safe 422 details (short excerpts, finite numbers only, text
that UTF-8 can carry), and messages cleared of the server's own paths."""

from __future__ import annotations

import math
import re
from pathlib import Path

_FLIGHTS = re.compile(r"(?:^|/)(flights/.*)")


def hide_server_paths(text: str, root: str | Path) -> str:
    """``text`` with every path under the server's data directory ``root`` shown as the file's
    place in its survey (``flights/f1/gnss.csv``) or its bare name (``dem.tif``): a reader's or
    GDAL's message may name the staged file by its absolute path, and the server's layout is not
    the client's business."""
    base = str(root).rstrip("/\\")
    if not base or base not in text:
        return text

    def short(m: re.Match) -> str:
        rest = (m.group(1) or "").replace("\\", "/").strip("/")
        f = _FLIGHTS.search(rest)
        return f.group(1) if f else (rest.rsplit("/", 1)[-1] or "the data directory")

    return re.sub(re.escape(base) + r"([/\\][^\s'\"]*)?", short, text)


def _text(s: str) -> str:
    """``s`` writable as UTF-8: a lone surrogate (JSON may escape one, ``"\\ud800"``) as its escape."""
    return s.encode("utf-8", "backslashreplace").decode("utf-8")


def _safe_value(v, depth: int = 0):
    """A request value echoed in a 422: finite numbers, short strings, shallow containers."""
    if isinstance(v, float) and not math.isfinite(v):
        return str(v)
    if isinstance(v, (bool, int, float)) or v is None:
        return v if not isinstance(v, int) or abs(v) < 2**63 else str(v)[:40] + "…"
    if isinstance(v, (list, tuple, dict)):
        if depth >= 2:
            return f"<{type(v).__name__} of {len(v)}>"
        items = list(v.items())[:20] if isinstance(v, dict) else list(v)[:20]
        if isinstance(v, dict):
            return {_text(str(k)[:100]): _safe_value(x, depth + 1) for k, x in items}
        return [_safe_value(x, depth + 1) for x in items]
    r = str(v)
    return _text(r if len(r) <= 100 else f"{r[:80]}… ({len(r)} characters)")


def validation_detail(errors) -> list[dict]:
    """pydantic/FastAPI errors as JSON-safe dicts: loc, msg, type, a short ``input``, ``ctx`` as text."""
    out = []
    for e in errors:
        d = {"loc": [x if isinstance(x, int) else _text(str(x)[:100]) for x in e.get("loc", ())],
             "msg": _text(str(e.get("msg", ""))[:300]), "type": e.get("type")}
        if "Expected UploadFile" in d["msg"]:
            # a file part without a file name arrives as text: say what is wrong, do not echo it
            d["msg"] = "a file upload is expected here (this part has no file name, or is not a file)"
            out.append(d)
            continue
        if "input" in e:
            d["input"] = _safe_value(e["input"])
        if e.get("ctx"):
            d["ctx"] = {k: _safe_value(v) for k, v in e["ctx"].items()}
        out.append(d)
    return out[:20]
