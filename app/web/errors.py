"""Request validation errors as JSON-safe 422 details (short excerpts, finite numbers only, text
that UTF-8 can carry)."""

from __future__ import annotations

import math


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
