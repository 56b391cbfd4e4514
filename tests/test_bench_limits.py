"""The cost models and the op counter of benchmarks/bench_limits.py (the benchmark itself is run by hand)."""

import json

import pytest

import benchmark_scripts  # tests/benchmark_scripts.py

B = benchmark_scripts.load("bench_limits")


def test_hashgrid_forward_model_counts_the_corner_gathers():
    one = B.hashgrid_forward_cost(1, 16, 2)
    assert one.bytes == 12 + 8 * 16 * 2 * 4 + 16 * 2 * 4  # point, gathered corners, output
    assert one.flops == 16 * (25 + 16 * 2)
    many = B.hashgrid_forward_cost(1000, 16, 2)
    assert many.bytes == 1000 * one.bytes and many.flops == 1000 * one.flops
    jac = B.hashgrid_forward_cost(1, 16, 2, jac=True)
    assert jac.bytes == one.bytes + 16 * 2 * 3 * 4  # the stored Jacobian written


def test_hashgrid_backward_model_table_gradient_scatters_and_zero_fills():
    L, F, T = 16, 2, 2 ** 16
    a = B.hashgrid_backward_cost(1, L, F, T, table=True, x=False)
    b = B.hashgrid_backward_cost(2, L, F, T, table=True, x=False)
    per_point = b.bytes - a.bytes
    assert per_point == 12 + L * F * 4 + 2 * 8 * L * F * 4  # point, output gradient, scatter read + write
    assert a.bytes - per_point == L * T * F * 4  # the zero-filled table gradient, whatever the points
    # the point gradient from the stored Jacobian reads less than recomputing it from the corners
    via_jac = B.hashgrid_backward_cost(1000, L, F, T, table=False, x=True, jac=True)
    via_corners = B.hashgrid_backward_cost(1000, L, F, T, table=False, x=True, jac=False)
    assert via_jac.bytes < via_corners.bytes and via_jac.flops < via_corners.flops


def test_floor_is_the_larger_of_the_two_and_the_row_ratio():
    peaks = {"cpu": {"gflops": 100.0, "gbs": 10.0}}
    ms, bound = B.floor_ms(B.Cost(flops=1e9, bytes=1e6), 100.0, 10.0)
    assert ms == pytest.approx(10.0) and bound == "flops"
    ms, bound = B.floor_ms(B.Cost(flops=1e6, bytes=1e9), 100.0, 10.0)
    assert ms == pytest.approx(100.0) and bound == "bytes"
    ms, bound = B.floor_ms(B.Cost(bytes=1e7), 100.0, 10.0)
    assert ms == pytest.approx(1.0) and bound == "-"
    row = B.make_row("x", "cpu", 50.0, B.Cost(flops=0, bytes=1e8), peaks, "note")
    assert row["floor_ms"] == pytest.approx(10.0) and row["x_floor"] == pytest.approx(5.0)
    assert row["gflop"] == 0 and row["mb"] == pytest.approx(100.0)
    text = B.format_table([row])
    assert "x floor" in text.splitlines()[0] and "x [cpu]" in text and "x: note" in text


def test_orb_bytes_of_one_level():
    assert B.orb_bytes(10, 20, 1, 1.2) == 5 * 200  # rgb read, grey written, grey read
    assert B.orb_bytes(10, 20, 8, 1.2) > B.orb_bytes(10, 20, 1, 1.2)


def test_counter_counts_operands_results_and_matmul_flops():
    import torch

    a, b = torch.ones(1000), torch.ones(1000)
    assert B.counted(lambda: a + b).bytes == 3 * 4000
    assert B.counted(lambda: a.view(10, 100).t()).bytes == 0  # views move nothing
    assert B.counted(lambda: a.add_(b)).bytes == 3 * 4000  # read a, b; write a
    assert B.counted(lambda: a.zero_()).bytes == 4000  # only written
    m = torch.ones(8, 16)
    c = B.counted(lambda: m @ torch.ones(16, 4))
    assert c.flops == 2 * 8 * 16 * 4
    assert c.bytes == 4 * (8 * 16 + 16 * 4 + 8 * 4) + 4 * 16 * 4  # + the ones() it made


def test_bad_arguments_exit_2_before_any_work(tmp_path, capsys):
    out = tmp_path / "limits.json"
    out.write_text(json.dumps({"old": 1}))
    assert B.main(["--reps", "0", "--json", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == ["error: --reps must be at least 1, got 0"]
    assert json.loads(out.read_text()) == {"old": 1}
