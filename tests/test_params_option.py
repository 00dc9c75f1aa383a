"""``--params`` (or ``$ARCLOUD_PARAMS``): the same algorithm settings, read the same way, for demo, eval,
serve and worker; a wrong one is refused with the same message: the field, what was expected, what came."""

from __future__ import annotations

import argparse

import pytest

from arcloud.argtypes import params_from_environment, params_given, params_overrides
from arcloud.cli import build_parser, main
from arcloud.core.types import Params
from arcloud.errors import ArcloudError, InvalidInput

IDENTITY = ((1.0, 0.0, 0.0, 0.0), (0.0, 1.0, 0.0, 0.0), (0.0, 0.0, 1.0, 0.0), (0.0, 0.0, 0.0, 1.0))

# JSON text -> the Params every command builds from it
ACCEPTED = [
    ("{}", Params()),
    ('{"voxel_size_m": 1}', Params(voxel_size_m=1.0)),
    ('{"up": [0, 1, 0]}', Params(up=(0.0, 1.0, 0.0))),  # a tuple given as a list
    ('{"world2aligned": [[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]}', Params(world2aligned=IDENTITY)),
    ('{"world2aligned": null, "layer_margin_m": null}', Params(world2aligned=None, layer_margin_m=None)),  # optional: None
    (
        '{"layer_classes": ["chair"], "split_classes": [], "floor_standing": ["table", "couch"]}',
        Params(layer_classes=("chair",), split_classes=(), floor_standing=("table", "couch")),
    ),
    (
        '{"class_aware": false, "erode_px": 3, "confirm_min_score": 0}',
        Params(class_aware=False, erode_px=3, confirm_min_score=0.0),
    ),
]

# JSON text -> the message every command refuses it with
REFUSED = [
    ('{"voxel": 0.04}', "params: expected fields of Params (apart_min_frames, "),  # an unknown field
    ('{"voxel_size_m": "0.04"}', "params.voxel_size_m: expected a finite number > 0, got '0.04'"),  # a wrong type
    ('{"voxel_size_m": null}', "params.voxel_size_m: expected a finite number > 0, got None"),  # not optional
    ('{"voxel_size_m": -1}', "params.voxel_size_m: expected a finite number > 0, got -1"),
    ('{"erode_px": 1.5}', "params.erode_px: expected an integer >= 0, got 1.5"),
    ('{"class_aware": 1}', "params.class_aware: expected True or False, got 1"),
    ('{"up": [0, 0]}', "params.up: expected a tuple of 3 finite numbers, not all 0, got (0, 0)"),
    ('{"layer_classes": ["sofa"]}', "params.layer_classes: expected a tuple of class names from"),
    ('{"world2aligned": [[1, 0], [0, 1]]}', "params.world2aligned: expected None or a (4, 4) tuple of tuples"),
    ('{"depth_min_m": 6}', "params.depth_max_m: expected more than depth_min_m (6.0), got 5.0"),  # a combination
]


def _eval_params(tmp_path, params_text: str | None) -> Params:
    from arcloud.accuracy.cli import _params

    given = ["--params", params_text] if params_text is not None else []
    args = build_parser().parse_args(
        ["eval", "7scenes", "--root", str(tmp_path), "--detector", "sim:0", "--out", "o.json", *given]
    )
    return _params(args)


def _serve_params(params_text: str | None) -> Params:
    from arcloud.tools.service_cli import settings_from_args

    given = ["--params", params_text] if params_text is not None else []
    return settings_from_args(build_parser().parse_args(["serve", "--detector", "sim:0", *given])).make_params()


def _routes(tmp_path, monkeypatch: pytest.MonkeyPatch, text: str) -> dict:
    """What eval and serve make of ``text``, given as ``--params`` and as ``$ARCLOUD_PARAMS``: the Params, or the
    refusal's message."""
    outcomes = {}
    routes = {
        "eval --params": lambda: _eval_params(tmp_path, text),
        "serve --params": lambda: _serve_params(text),
        "eval $ARCLOUD_PARAMS": lambda: _eval_params(tmp_path, None),
        "serve $ARCLOUD_PARAMS": lambda: _serve_params(None),
    }
    for route, run in routes.items():
        if "ARCLOUD_PARAMS" in route:
            monkeypatch.setenv("ARCLOUD_PARAMS", text)
        else:
            monkeypatch.delenv("ARCLOUD_PARAMS", raising=False)
        try:
            outcomes[route] = run()
        except ArcloudError as exc:  # serve: "invalid settings (...): <the message>"; eval: the message
            outcomes[route] = str(exc).removeprefix("invalid settings (options or ARCLOUD_* variables): ")
    return outcomes


@pytest.mark.parametrize(("text", "params"), ACCEPTED)
def test_every_command_builds_the_same_params(tmp_path, monkeypatch: pytest.MonkeyPatch, text: str, params: Params) -> None:
    outcomes = _routes(tmp_path, monkeypatch, text)
    for route, outcome in outcomes.items():
        assert outcome == params, route
        assert all(type(getattr(outcome, name)) is type(getattr(params, name)) for name in ("voxel_size_m", "confirm_min_score"))


@pytest.mark.parametrize(("text", "says"), REFUSED)
def test_every_command_refuses_the_same_json_saying_the_same(
    tmp_path, monkeypatch: pytest.MonkeyPatch, text: str, says: str
) -> None:
    outcomes = _routes(tmp_path, monkeypatch, text)
    messages = set(outcomes.values())
    assert len(messages) == 1, outcomes
    assert messages.pop().startswith(says)


def test_the_service_refuses_the_fields_that_are_its_own_settings() -> None:
    """The store's lock times are settings of the service (ARCLOUD_LOCK_TTL_S, ...): in its params they would
    be a second name for them. The commands without those settings take them in --params."""
    with pytest.raises(ArcloudError, match=r"params.lock_ttl_s: set it as its own setting \(ARCLOUD_LOCK_TTL_S\)"):
        _serve_params('{"lock_ttl_s": 3}')
    assert params_given({"lock_ttl_s": 3}).lock_ttl_s == 3.0


def test_params_must_be_a_json_object(monkeypatch: pytest.MonkeyPatch) -> None:
    for text in ("[1]", "{voxel_size_m: 1}", "0.04"):
        with pytest.raises(argparse.ArgumentTypeError, match="expected a JSON object"):
            params_overrides(text)
    monkeypatch.delenv("ARCLOUD_PARAMS", raising=False)
    assert params_from_environment() == {}
    monkeypatch.setenv("ARCLOUD_PARAMS", "0.04")
    with pytest.raises(InvalidInput, match="ARCLOUD_PARAMS: expected a JSON object"):
        params_from_environment()


def test_demo_and_worker_take_params(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["demo", "--params", '{"voxel_size_m": 0}', "--frames", "1"]) == 2
    assert "params.voxel_size_m: expected a finite number > 0, got 0" in capsys.readouterr().err
    from arcloud.tools.service_cli import settings_from_args

    args = build_parser().parse_args(
        ["worker", "--redis", "redis://127.0.0.1:1/0", "--detector", "sim:0", "--params", '{"up": [0, 1, 0]}']
    )
    assert settings_from_args(args).make_params().up == (0.0, 1.0, 0.0)


def test_eval_sets_its_voxel_size_on_top_of_params(tmp_path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv("ARCLOUD_PARAMS", raising=False)
    from arcloud.accuracy.cli import _params

    args = build_parser().parse_args(
        ["eval", "scannet", "--root", str(tmp_path), "--detector", "sim:0", "--out", "o.json"]
        + ["--params", '{"up": [0, 1, 0]}', "--voxel-size-m", "0.03"]
    )
    assert _params(args) == Params(up=(0.0, 1.0, 0.0), voxel_size_m=0.03)
