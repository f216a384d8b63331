"""The precision study: bf16 products emulated in float32 give what the native bf16 kernels give, and a fit
records its steps in both precisions."""

import torch
from torch import nn

from benchmarks.speed.train_step import pair_batch
from benchmarks.studies.precision.emulated import Bf16ProductsInFp32
from benchmarks.studies.precision.fit_pairs import fit


def _step(module: nn.Module, x: torch.Tensor, emulate: bool) -> tuple[torch.Tensor, list[torch.Tensor]]:
    module.zero_grad()
    x = x.clone().requires_grad_()
    with Bf16ProductsInFp32() if emulate else torch.autocast("cpu", enabled=False):
        with torch.autocast("cpu", dtype=torch.bfloat16):
            y = module(x)
        (y.float() * torch.linspace(-1, 1, y.numel()).view_as(y)).sum().backward()
    return y, [x.grad, *(p.grad for p in module.parameters())]


def test_emulated_products_match_the_native_bf16_kernels():
    """Linear (mm/addmm), a batched product (bmm) and a convolution, forward and backward: the same bf16
    results (bf16 operands, float32 accumulation) up to one bf16 rounding of a differently ordered sum."""
    torch.manual_seed(0)
    cases = [(nn.Linear(24, 16), torch.randn(2, 40, 24)), (nn.Conv1d(6, 8, 1), torch.randn(2, 6, 30)),
             (nn.Conv2d(4, 8, 1), torch.randn(2, 4, 10, 5))]
    for module, x in cases:
        native, native_grads = _step(module, x, emulate=False)
        emulated, emulated_grads = _step(module, x, emulate=True)
        assert native.dtype == emulated.dtype == torch.bfloat16
        torch.testing.assert_close(emulated.float(), native.float(), rtol=2 ** -7, atol=1e-3)
        for a, b in zip(emulated_grads, native_grads):
            assert a.dtype == b.dtype
            torch.testing.assert_close(a.float(), b.float(), rtol=2 ** -7, atol=1e-3)
    a, b = torch.randn(3, 20, 12).bfloat16(), torch.randn(3, 12, 9).bfloat16()
    with Bf16ProductsInFp32():
        emulated = torch.bmm(a, b)
    torch.testing.assert_close(emulated.float(), torch.bmm(a, b).float(), rtol=2 ** -7, atol=1e-3)


def test_float32_operations_are_untouched():
    a, b = torch.randn(8, 8), torch.randn(8, 8)
    with Bf16ProductsInFp32():
        assert torch.equal(a @ b, torch.mm(a, b))


def test_a_fit_records_its_steps_in_both_precisions():
    batch = pair_batch(4, 64, torch.device("cpu"))
    for precision, kernels in (("fp32", "native"), ("bf16", "emulated")):
        rows = fit("omnet", 0.0625, 0, precision, ["iterations.*.regressor"] if precision == "bf16" else [], batch,
                   steps=2, record={1, 2}, lr=1e-3, kernels=kernels)
        assert [r["step"] for r in rows] == [1, 2]
        assert all(0 <= r["rot_deg"] <= 180 and r["loss"] > 0 for r in rows)
        assert rows[0]["kernels"] == ("emulated" if precision == "bf16" else "")


def _fits(tmp_path, bf16_errors: list[float]) -> str:
    import pandas as pd

    rows = []
    for seed, (a, b) in enumerate(zip([10.0, 12.0, 14.0], bf16_errors)):
        for precision, error in (("fp32", a), ("bf16", b)):
            rows.append({"method": "omnet", "width": 0.25, "seed": seed, "precision": precision,
                         "kernels": "emulated" if precision == "bf16" else "", "fp32_modules": "", "step": 100,
                         "loss": 1.0, "rot_deg": error, "trans": 0.1, "cpu_s": 1.0})
    path = tmp_path / "fits.csv"
    pd.DataFrame(rows).to_csv(path, index=False)
    return str(path)


def test_the_verdict_compares_the_bf16_mean_with_the_float32_seeds_range(tmp_path, capsys):
    from benchmarks.studies.precision.report import main
    from tests.helpers.markdown import markdown_table

    assert main([_fits(tmp_path, [11.0, 13.0, 15.0])]) == 0
    row = markdown_table(capsys.readouterr().out)[1].iloc[0]
    assert (row["fp32 Error(R) mean (min–max)"], row["bf16 − fp32"], row["verdict"]) == ("12.00 (10.00–14.00)", "+1.00", "same")
    assert main([_fits(tmp_path, [20.0, 22.0, 24.0])]) == 0
    assert markdown_table(capsys.readouterr().out)[1].iloc[0]["verdict"] == "changes (bf16 higher)"
    assert main([_fits(tmp_path, [2.0, 12.0, 40.0])]) == 0  # mean 18, but the bf16 seeds' range holds the float32 mean
    assert markdown_table(capsys.readouterr().out)[1].iloc[0]["verdict"] == "same"
    assert main([str(tmp_path / "none.csv")]) == 2


def test_the_timer_counts_every_operation_with_the_products_apart():
    from benchmarks.studies.precision.projection import PRODUCT, TimedOps

    a, b = torch.randn(64, 32), torch.randn(32, 16)
    with TimedOps() as timed:
        product = torch.mm(a, b)
        total = (product + 1.0).sum()
        emulated = torch.mm(a.bfloat16(), b.bfloat16())
    assert timed.calls == 6 and set(timed.seconds) == {PRODUCT, "add", "sum", "_to_copy"}
    assert emulated.dtype == torch.bfloat16 and torch.isfinite(total)
    assert all(seconds >= 0 for seconds in timed.seconds.values())


def test_the_projection_divides_only_the_product_time_by_the_ratio():
    import math

    from benchmarks.studies.precision.projection import project

    # float32 step 10 s of which 8 s products; the bf16 step's other work 3 s; products 4x faster: 3 + 8 / 4 = 5 s
    p = project(10.0, 8.0, 3.0, flops=4e9, mm32_gflops=2.0, ratio=4.0)
    assert p["projected_s"] == 5.0 and p["speedup"] == 2.0
    assert math.isclose(p["pct_of_bf16_mm"], 100 * 4e9 / 5.0 / 8e9)  # 4 GFLOP in 5 s against 4 x 2 GFLOP/s
    free = project(10.0, 8.0, 3.0, flops=4e9, mm32_gflops=2.0, ratio=math.inf)
    assert free["projected_s"] == 3.0 and math.isnan(free["pct_of_bf16_mm"])
