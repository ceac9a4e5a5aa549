"""Unknown keys of a stage's settings against its defaults, found in one place.

Every stage has a ``DEFAULTS`` dict (the key and its default for each setting it knows);
its settings come from the config block of the same name. :func:`unknown_keys` lists the
keys given that are not in the defaults (and :func:`text_for_numbers` the values given
as text where the default is a number), dotted (``masks.classical.thresold_low``) for
those inside a nested section. The stages raise on them (:func:`check_keys`) when a job
starts, and the workflow (``workflow/rules/common.smk``) checks every stage's block of
the config with the same function before any job runs, one line per unknown key.

This module imports nothing but the standard library, so the workflow can read it while
it builds the DAG.
"""

from __future__ import annotations

import difflib
from collections.abc import Mapping


def unknown_keys(defaults: Mapping, given: Mapping | None, section: str) -> list[str]:
    """The keys of ``given`` that ``defaults`` lacks, as ``section.key``, in given order.

    A key whose default is a mapping is a nested section: when it is given as a mapping
    too, its keys are checked the same way (``section.key.subkey``). A nested section
    given as something else is not an unknown key (the stage says what it should be).
    """
    out: list[str] = []
    for key, value in (given or {}).items():
        where = f"{section}.{key}"
        if key not in defaults:
            out.append(where)
        elif isinstance(defaults[key], Mapping) and isinstance(value, Mapping):
            out.extend(unknown_keys(defaults[key], value, where))
    return out


def text_for_numbers(defaults: Mapping, given: Mapping | None, section: str) -> list[str]:
    """``section.key: ...`` for each value of ``given`` that is a number written as text
    where ``defaults`` holds a number (nested sections recursed, as
    :func:`unknown_keys`). YAML 1.1, which Snakemake and PyYAML read, takes a number with
    an exponent and no decimal point (``5e-5``) for text, which a stage would otherwise
    compare with numbers: the message says how to write it."""
    out: list[str] = []
    for key, value in (given or {}).items():
        where = f"{section}.{key}"
        default = defaults.get(key) if key in defaults else None
        if isinstance(default, Mapping) and isinstance(value, Mapping):
            out.extend(text_for_numbers(default, value, where))
        elif (
            isinstance(default, int | float)
            and not isinstance(default, bool)
            and isinstance(value, str)
        ):
            try:  # other text may be a setting's named value (mesh: speed_max: session)
                number = float(value)
            except ValueError:
                continue
            out.append(
                f"{where}: {value!r} is text, a number is expected: write {number!r} "
                f"(YAML reads {value} as text)"
            )
    return out


def known_keys(defaults: Mapping, dotted: str) -> list[str]:
    """The keys known beside ``dotted`` (a name from :func:`unknown_keys`), sorted."""
    level = defaults
    for key in dotted.split(".")[1:-1]:
        level = level[key]
    return sorted(map(str, level))


#: A hint lists the known keys when there are at most this many (else it says where).
MAX_LISTED = 25


def key_hint(defaults: Mapping, dotted: str, see: str = "") -> str:
    """What ``dotted`` (a name from :func:`unknown_keys`) may have meant: the close known
    keys (``did you mean iters_first?``), or else the keys known beside it (a list, or
    their number and ``see``, where they are documented, when there are many)."""
    known = known_keys(defaults, dotted)
    close = difflib.get_close_matches(dotted.rsplit(".", 1)[-1], known, n=3, cutoff=0.7)
    if close:
        return f"did you mean {' or '.join(close)}?"
    if len(known) <= MAX_LISTED:
        return f"known: {', '.join(known)}"
    return f"not one of the {len(known)} known keys" + (f"; see {see}" if see else "")


def check_keys(defaults: Mapping, given: Mapping | None, section: str, see: str = "") -> None:
    """Raise ValueError naming every key of ``given`` that ``defaults`` lacks, and every
    value that is text where the default is a number (:func:`text_for_numbers`)."""
    bad = [
        f"unknown parameter {k} ({key_hint(defaults, k, see)})"
        for k in unknown_keys(defaults, given, section)
    ]
    bad += text_for_numbers(defaults, given, section)
    if bad:
        raise ValueError("; ".join(bad))
