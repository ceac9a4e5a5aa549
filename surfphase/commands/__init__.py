"""Subcommands of ``surfphase``; each module defines ``register(subparsers)``.

Optionally also ``register_bench(bench_subparsers)`` for ``surfphase bench NAME``.

Shared by the modules: :func:`read_json_object`, the one reader of ``--params-json`` (and
the other options that take a JSON object: ``--fit-json``, ``bench fit --params``).
"""

from __future__ import annotations

import json
from pathlib import Path


def _names_json_file(text: str) -> bool:
    """Whether an option's value is the path of an existing JSON file, not JSON text.

    A path is an existing file that ends in ``.json`` or whose value does not begin with
    ``{`` (so that an inline object is never mistaken for a file name).
    """
    path = Path(text)
    if text.lstrip().startswith("{") and path.suffix != ".json":
        return False
    try:
        return path.is_file()
    except OSError:  # e.g. a name longer than the file system allows: not a path
        return False


def read_json_object(text: str | None, option: str = "--params-json", what: str = "") -> dict:
    """The JSON object an option gives: inline JSON text or the path of a file holding it.

    ``text`` is the option's value as typed; ``None`` or empty gives ``{}``. It is read
    from the file it names when :func:`_names_json_file` says so, else parsed as JSON.
    Errors are :class:`ValueError` naming ``option``: ``OPTION: not valid JSON (...)``
    and ``OPTION: expected a JSON object`` (followed by `` of WHAT`` when ``what`` is
    given, e.g. ``"fit parameters"``).
    """
    if not text:
        return {}
    src = Path(text).read_text() if _names_json_file(text) else text
    try:
        obj = json.loads(src)
    except ValueError as e:
        raise ValueError(f"{option}: not valid JSON ({e})") from e
    if not isinstance(obj, dict):
        raise ValueError(f"{option}: expected a JSON object" + (f" of {what}" if what else ""))
    return obj
