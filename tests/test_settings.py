"""One check of unknown setting keys for every stage (surfphase.settings)."""

from __future__ import annotations

import subprocess
import sys

import pytest

from surfphase.settings import check_keys, key_hint, text_for_numbers, unknown_keys

DEFAULTS = {
    "backend": "classical",
    "classical": {"threshold_low": 0.08, "threshold_high": 0.2},
    "frames": None,
    "far_views": [4, 5],
}


def test_unknown_keys_are_dotted_and_nested_sections_recursed():
    given = {
        "backend": "sam",
        "classical": {"threshold_low": 0.1, "thresold_high": 0.3},
        "framez": 3,
        "far_views": [1],
    }
    assert unknown_keys(DEFAULTS, given, "masks") == [
        "masks.classical.thresold_high",
        "masks.framez",
    ]


def test_known_and_empty_settings_have_no_unknown_keys():
    assert unknown_keys(DEFAULTS, {}, "masks") == []
    assert unknown_keys(DEFAULTS, None, "masks") == []
    assert unknown_keys(DEFAULTS, {"classical": {}, "frames": 5}, "masks") == []
    # A nested section given as something else is the stage's to refuse, not unknown;
    # a mapping given where the default is not one is a value, not a section.
    assert unknown_keys(DEFAULTS, {"classical": 3, "frames": {"x": 1}}, "masks") == []


def test_hint_names_close_keys_or_lists_the_known_ones():
    assert key_hint(DEFAULTS, "masks.classical.thresold_low") == "did you mean threshold_low?"
    assert key_hint(DEFAULTS, "masks.zzz") == "known: backend, classical, far_views, frames"
    many = {f"key{i:02d}": i for i in range(40)}
    assert key_hint(many, "fit.zzz", see="X.DEFAULTS") == (
        "not one of the 40 known keys; see X.DEFAULTS"
    )


def test_check_keys_raises_naming_every_unknown_key():
    check_keys(DEFAULTS, {"backend": "sam"}, "masks")
    with pytest.raises(ValueError, match="unknown parameter") as e:
        check_keys(DEFAULTS, {"classical": {"thresold_low": 1}, "zzz": 0}, "masks")
    msg = str(e.value)
    assert "masks.classical.thresold_low (did you mean threshold_low?)" in msg
    assert "masks.zzz" in msg


def test_a_number_yaml_reads_as_text_is_named_with_its_spelling():
    """``5e-5`` in a YAML config is text (YAML 1.1, PyYAML's and Snakemake's reader): the
    stage names the key and how to write it, nested sections too; other text (a named
    value such as ``speed_max: session``) and real numbers pass."""
    import yaml

    from surfphase.masks.params import DEFAULTS as MASKS
    from surfphase.mesh.params import DEFAULTS as MESH

    given = yaml.safe_load("associate:\n  nucleation_height: 5e-5\n")
    assert given["associate"]["nucleation_height"] == "5e-5"  # the reader, as documented
    with pytest.raises(ValueError, match=r"masks.associate.nucleation_height: '5e-5' is text"):
        check_keys(MASKS, given, "masks")
    assert "write 5e-05" in text_for_numbers(MASKS, given, "masks")[0]
    assert text_for_numbers(MESH, {"speed_max": "session", "voxels": 32}, "mesh") == []
    assert (
        text_for_numbers(
            MASKS, yaml.safe_load("associate:\n  nucleation_height: 5.0e-5\n"), "masks"
        )
        == []
    )


def test_stage_defaults_import_without_torch():
    """The workflow reads the stages' DEFAULTS while it builds the DAG: no torch."""
    code = (
        "import sys\n"
        "import surfphase.fit.params, surfphase.mesh.params, surfphase.views_params\n"
        "import surfphase.masks.stage, surfphase.settings\n"
        "print('torch' in sys.modules)\n"
    )
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert r.stdout.strip() == "False"


def test_stage_modules_hold_the_moved_defaults():
    from surfphase import views, views_params
    from surfphase.fit import params as fit_params
    from surfphase.fit import stage, stage2
    from surfphase.mesh import params as mesh_params
    from surfphase.mesh import stage as mesh_stage

    assert stage.DEFAULTS is fit_params.DEFAULTS
    assert stage2.DEFAULTS is fit_params.STAGE2_DEFAULTS
    assert stage2.FIT_OVERRIDES is fit_params.FIT_OVERRIDES
    assert mesh_stage.DEFAULTS is mesh_params.DEFAULTS
    assert views.DEFAULTS is views_params.DEFAULTS


def test_each_stage_default_is_written_once():
    """The config schema gives no default for a key whose stage module holds it (the
    module's dict is the one source; the workflow merges it), and the refine block's
    keys are exactly those of its defaults."""
    from pathlib import Path

    import yaml

    from surfphase.fit.params import DEFAULTS as FIT
    from surfphase.fit.params import STAGE2_DEFAULTS
    from surfphase.masks.params import DEFAULTS as MASKS
    from surfphase.mesh.params import DEFAULTS as MESH
    from surfphase.views_params import REFINE_DEFAULTS

    root = Path(__file__).resolve().parents[1]
    schema = yaml.safe_load((root / "workflow/schemas/config.schema.yaml").read_text())
    owners = {"fit": FIT, "fit2": STAGE2_DEFAULTS, "masks": MASKS, "mesh": MESH}
    owners["refine"] = REFINE_DEFAULTS
    twice = {
        f"{block}.{key}"
        for block, defaults in owners.items()
        for key, prop in schema["properties"][block].get("properties", {}).items()
        if key in defaults and "default" in prop
    }
    assert not twice
    assert set(schema["properties"]["refine"]["properties"]) == set(REFINE_DEFAULTS)
    assert STAGE2_DEFAULTS["far_views"] == REFINE_DEFAULTS["far_views"]


def test_the_example_config_shows_the_stage_defaults():
    """config/config.yaml (the demo campaign's, and the example users copy) lists stage
    settings with their values: each equals its stage module's default, so it cannot
    drift from them; the demo's own choices are named here."""
    from pathlib import Path

    import yaml

    from surfphase.fit.params import DEFAULTS as FIT
    from surfphase.fit.params import STAGE2_DEFAULTS
    from surfphase.masks.params import DEFAULTS as MASKS
    from surfphase.mesh.params import DEFAULTS as MESH
    from surfphase.views_params import REFINE_DEFAULTS

    demo_choices = {"refine.enabled"}  # the demo refines (it ships clips)
    workflow_keys = {"mesh.window"}  # the workflow's own (schema default)
    root = Path(__file__).resolve().parents[1]
    cfg = yaml.safe_load((root / "config/config.yaml").read_text())
    differ = []

    def walk(prefix: str, defaults: dict, values: dict) -> None:
        for key, value in values.items():
            name = f"{prefix}.{key}"
            if isinstance(value, dict) and isinstance(defaults.get(key), dict):
                walk(name, defaults[key], value)
            elif name not in demo_choices | workflow_keys and defaults.get(key, object()) != value:
                differ.append(name)

    owners = {"fit": FIT, "fit2": STAGE2_DEFAULTS, "masks": MASKS, "mesh": MESH}
    owners["refine"] = REFINE_DEFAULTS
    for block, defaults in owners.items():
        walk(block, defaults, cfg.get(block) or {})
    assert not differ
