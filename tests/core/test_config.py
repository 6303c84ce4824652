from dataclasses import dataclass, field
from typing import Literal

import pytest

from voxfusion.core.config import apply_overrides, config_from_dict, config_to_dict, load_config, parse_overrides
from voxfusion.core.errors import ConfigError


@dataclass(frozen=True)
class Inner:
    lr: float = 0.01
    iters: int = 10
    mode: Literal["a", "b"] = "a"


@dataclass(frozen=True)
class Outer:
    inner: Inner = field(default_factory=Inner)
    name: str = "x"
    size: tuple[int, int] = (4, 3)
    device: str | None = None


def test_yaml_base_and_overrides(tmp_path):
    (tmp_path / "base.yaml").write_text("inner:\n  lr: 0.5\nname: base\n")
    (tmp_path / "child.yaml").write_text("base: base.yaml\ninner:\n  iters: 3\n")
    cfg = load_config(Outer, tmp_path / "child.yaml", ["inner.mode=b", "size=[8, 6]", "device=cpu"])
    assert cfg == Outer(Inner(lr=0.5, iters=3, mode="b"), name="base", size=(8, 6), device="cpu")
    assert config_to_dict(cfg)["size"] == [8, 6]


def test_int_promotes_to_float_but_not_reverse():
    assert apply_overrides(Outer(), ["inner.lr=1"]).inner.lr == 1.0
    with pytest.raises(ConfigError, match="inner.iters"):
        apply_overrides(Outer(), ["inner.iters=1.5"])


def test_exponent_without_dot_is_a_number():
    # YAML 1.1 reads "1e6" as a string; a float field takes it as the number the user meant
    assert apply_overrides(Outer(), ["inner.lr=1e6"]).inner.lr == 1e6
    with pytest.raises(ConfigError, match="inner.lr"):
        apply_overrides(Outer(), ["inner.lr=fast"])


@pytest.mark.parametrize(
    "items, key",
    [(["inner.nope=1"], "inner.nope"), (["inner.mode=c"], "inner.mode"), (["novalue"], "novalue")],
)
def test_bad_overrides_name_the_key(items, key):
    with pytest.raises(ConfigError) as e:
        apply_overrides(Outer(), items)
    assert e.value.field == key


def test_unknown_keys_say_what_was_meant():
    """A misspelt key names the nearest valid one; a dotted key in a mapping (the --set spelling, e.g. in an HTTP
    request's JSON) says how to nest it; neither hides the valid keys."""
    with pytest.raises(ConfigError, match=r"did you mean 'iters'\?.*valid keys here: \['iters', 'lr', 'mode'\]") as e:
        apply_overrides(Outer(), ["inner.iter=3"])
    assert e.value.field == "inner.iter"
    with pytest.raises(ConfigError, match=r'nest them, e.g. \{"inner": \{"iters": 3\}\}') as e:
        config_from_dict(Outer, {"inner.iters": 3})
    assert e.value.field == "inner.iters"
    with pytest.raises(ConfigError) as e:
        config_from_dict(Outer, {"zzz": 1})
    assert "did you mean" not in str(e.value) and "valid keys here" in str(e.value)


def test_missing_file(tmp_path):
    with pytest.raises(ConfigError, match="not found"):
        load_config(Outer, tmp_path / "missing.yaml")


def test_parse_overrides_nested():
    assert parse_overrides(["a.b=1", "a.c=true", "d=hi"]) == {"a": {"b": 1, "c": True}, "d": "hi"}


def test_every_shipped_preset_loads():
    from voxfusion.core.slam.presets import KIND_PRESETS, PRESET_ALIASES, load_preset, preset_names

    names = preset_names()
    assert {"default", "cpu", "iphone", "paper", *KIND_PRESETS.values()} <= set(names)
    for name in [*names, *PRESET_ALIASES, *(f"{kind}+cpu" for kind in KIND_PRESETS.values())]:
        load_preset(name)
