"""``--params`` (or ``$ARCLOUD_PARAMS``): the same algorithm settings, read the same way, for demo, eval,
serve and worker; a wrong one is refused with what was expected."""

from __future__ import annotations

import argparse

import pytest

from arcloud.argtypes import make_params, params_from_environment, params_overrides
from arcloud.cli import build_parser, main
from arcloud.core.types import Params
from arcloud.errors import InvalidInput


def test_overrides_become_checked_params() -> None:
    params = make_params(params_overrides('{"voxel_size_m": 0.04, "up": [0, 1, 0], "floor_standing": ["chair"]}'))
    assert params == Params(voxel_size_m=0.04, up=(0.0, 1.0, 0.0), floor_standing=("chair",))
    assert make_params({}) == Params()
    with pytest.raises(InvalidInput, match="params: expected fields of Params .* got 'voxel'"):
        make_params({"voxel": 0.04})
    with pytest.raises(InvalidInput, match="Params.voxel_size_m: expected a finite number > 0, got -1"):
        make_params({"voxel_size_m": -1})
    for text in ("[1]", "{voxel_size_m: 1}", "0.04"):
        with pytest.raises(argparse.ArgumentTypeError, match="expected a JSON object"):
            params_overrides(text)


def test_the_environment_variable_is_read_the_same_way(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv("ARCLOUD_PARAMS", raising=False)
    assert params_from_environment() == {}
    monkeypatch.setenv("ARCLOUD_PARAMS", '{"voxel_size_m": 0.04}')
    assert params_from_environment() == {"voxel_size_m": 0.04}
    monkeypatch.setenv("ARCLOUD_PARAMS", "0.04")
    with pytest.raises(InvalidInput, match="ARCLOUD_PARAMS: expected a JSON object"):
        params_from_environment()


def test_demo_and_serve_take_params(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["demo", "--params", '{"voxel_size_m": 0}', "--frames", "1"]) == 2
    assert "Params.voxel_size_m: expected a finite number > 0, got 0" in capsys.readouterr().err
    from arcloud.tools.service_cli import settings_from_args

    args = build_parser().parse_args(["serve", "--detector", "sim:0", "--params", '{"voxel_size_m": 0.04}'])
    assert settings_from_args(args).make_params().voxel_size_m == 0.04
    args = build_parser().parse_args(
        ["worker", "--redis", "redis://127.0.0.1:1/0", "--detector", "sim:0", "--params", '{"up": [0, 1, 0]}']
    )
    assert settings_from_args(args).make_params().up == (0.0, 1.0, 0.0)


def test_eval_takes_params(capsys: pytest.CaptureFixture[str], tmp_path) -> None:
    from arcloud.accuracy.cli import _params

    args = build_parser().parse_args(
        [
            "eval",
            "7scenes",
            "--root",
            str(tmp_path),
            "--detector",
            "sim:0",
            "--out",
            "o.json",
            "--params",
            '{"voxel_size_m": 0.04}',
        ]
    )
    assert _params(args).voxel_size_m == 0.04
    args = build_parser().parse_args(
        [
            "eval",
            "scannet",
            "--root",
            str(tmp_path),
            "--detector",
            "sim:0",
            "--out",
            "o.json",
            "--params",
            '{"up": [0, 1, 0]}',
            "--voxel-size-m",
            "0.03",
        ]
    )
    assert _params(args) == Params(up=(0.0, 1.0, 0.0), voxel_size_m=0.03)
