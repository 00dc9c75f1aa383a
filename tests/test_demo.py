"""`arcloud demo`, small: the results file has the documented shape and the pictures are written."""

import json

import pytest

from arcloud.cli import main


@pytest.mark.timeout(180)
def test_demo_writes_table1_results_and_pictures(tmp_path, capsys):
    out = tmp_path / "demo"
    assert main(["demo", "--out", str(out), "--frames", "40", "--runs", "2", "--users", "4,10", "--no-progress"]) == 0
    results = json.loads((out / "results.json").read_text())
    rows = results["table1"]
    assert [(r["approach"], r["users"], r["runs"]) for r in rows] == [
        ("centralized", 1, 1),
        ("distributed", 4, 2),
        ("distributed", 10, 2),
    ]
    for row in rows:
        assert set(row) >= {"map25_mean", "map25_var", "map50_mean", "map50_var"}
        assert 0.0 <= row["map50_mean"] <= row["map25_mean"] <= 1.0 and row["map25_var"] >= 0.0
    assert rows[0]["map25_mean"] > 0.0  # 40 frames see some objects well enough
    assert results["scene"]["frames"] == 40 and results["scene"]["objects"] > 0
    for name in results["pictures"].values():
        assert (out / name).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    served = results["served"]["centralized_1"]
    assert served["n_served"] <= served["n_objects"] and 0.0 <= served["served_precision25"] <= 1.0
    printed = capsys.readouterr().out
    assert "centralized" in printed and "results.json" in printed and "served (confirmed)" in printed


def test_demo_refuses_bad_arguments(capsys):
    with pytest.raises(SystemExit) as info:
        main(["demo", "--users", "0,5"])
    assert info.value.code == 2
    assert "expected user counts >= 1" in capsys.readouterr().err
