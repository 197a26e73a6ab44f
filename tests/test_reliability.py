"""Reliability defects found from outside: each case reproduces one on a self-made file first."""

import shutil
from pathlib import Path

import numpy as np
import pytest

import sphere_nlp
from sphere_nlp import errors
from sphere_nlp.cli import main
from sphere_nlp.mesh_io import load_mesh, write_mesh
from sphere_nlp.shapes import octahedron

MODELS = Path(__file__).resolve().parent.parent / "models"


def run_cli(capsys, *args):
    status = main([str(a) for a in args])
    return status, capsys.readouterr().err


def test_a_byte_order_mark_does_not_hide_the_first_line(tmp_path):
    V, F = octahedron()
    plain = tmp_path / "plain.obj"
    write_mesh(plain, V, F)
    marked = tmp_path / "marked.obj"
    marked.write_bytes(b"\xef\xbb\xbf" + plain.read_bytes())
    V1, F1 = load_mesh(plain)
    V2, F2 = load_mesh(marked)
    assert np.array_equal(V1, V2) and np.array_equal(F1, F2) and len(V2) == 6


def test_the_default_output_name_keeps_inner_dots(tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)
    shutil.copy(MODELS / "cylinder.off", tmp_path / "cylinder.v1.off")
    status, err = run_cli(capsys, "cylinder.v1.off", "-q")
    assert status == 0, err
    assert (tmp_path / "cylinder.v1.sphere.off").exists() and not (tmp_path / "cylinder.sphere.off").exists()


@pytest.mark.parametrize("extra", [
    ["-o", "{input}"],                                             # would replace the input
    ["-o", "x.obj", "--textured-input", "x.obj"],
    ["-o", "x.off", "--save-solution", "x.off"],
    ["--png", "p.png", "--report", "p.png"],
])
def test_outputs_must_differ_from_the_input_and_each_other(tmp_path, capsys, monkeypatch, extra):
    monkeypatch.chdir(tmp_path)
    source = tmp_path / "cyl.off"
    shutil.copy(MODELS / "cylinder.off", source)
    before = source.read_bytes()
    status, err = run_cli(capsys, source, *[a.format(input=source) for a in extra])
    assert status == 2, err
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("sphere-nlp: error: cannot write"), err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["cyl.off"] and source.read_bytes() == before


@pytest.mark.parametrize("option,value", [("--max-time", "nan"), ("--max-time", "0"), ("--max-time", "-1"),
                                          ("--max-time", "inf"), ("--max-iter", "0"), ("--max-iter", "-5")])
def test_limits_must_be_positive(tmp_path, capsys, monkeypatch, option, value):
    monkeypatch.chdir(tmp_path)
    status, err = run_cli(capsys, MODELS / "cylinder.off", option, value)
    assert status == 2 and len(err.strip().splitlines()) == 1 and option.lstrip("-").replace("-", "_") in err, err
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("keywords", [dict(max_iter="abc"), dict(max_iter=2.5), dict(max_time=-1),
                                      dict(max_time=float("nan")), dict(angle_weight=float("nan")),
                                      dict(area_weight=float("inf")), dict(angle_weight=1j)])
def test_the_api_refuses_bad_values_with_usage_error(keywords):
    with pytest.raises(errors.UsageError):
        sphere_nlp.parameterize(octahedron(), **keywords)
