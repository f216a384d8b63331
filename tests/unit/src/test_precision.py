"""The run's precision: chosen from the method's verdict and the device's facts (faked here), an explicit
one honoured or refused in one line, the verdicts file well formed."""

import pytest
from omegaconf import OmegaConf

import src.run.precision as precision
from src.utils.errors import ConfigError
from src.run.precision import (BF16, FP32, Device, Verdict, choose_precision, cpu_flags, load_verdicts, run_precision,
                           settle_precision)
from tests.helpers.paths import ROOT

OMNET = "src.models.omnet.OMNet"
SAME = {OMNET: Verdict("same", "within the spread")}
CHANGES = {OMNET: Verdict("changes", "2x the error")}
AMX = Device("cpu", ("amx_bf16",), bf16_speedup=7.1)
ZEN2 = Device("cpu", (), bf16_speedup=0.02)


def test_cpu_flags_are_read_from_cpuinfo_text():
    text = "processor\t: 0\nvendor_id\t: AuthenticAMD\nflags\t\t: fpu avx2 amx_bf16 sse\n\nprocessor\t: 1\nflags\t: fpu\n"
    assert cpu_flags(text) == {"fpu", "avx2", "amx_bf16", "sse"}
    assert cpu_flags("Features\t: fp asimd bf16\n") == {"fp", "asimd", "bf16"}
    assert cpu_flags("no flags here") == frozenset()


def test_auto_takes_bf16_where_the_cpu_runs_it_fast_and_the_verdict_allows_it():
    choice = choose_precision("auto", OMNET, SAME, AMX)
    assert choice.precision == BF16
    assert "7.1x the float32 rate" in choice.reason and "amx_bf16" in choice.reason and "unchanged" in choice.reason


def test_auto_falls_back_to_fp32_where_bf16_is_emulated():
    choice = choose_precision("auto", OMNET, SAME, ZEN2)
    assert choice.precision == FP32
    assert "bf16 is emulated and slower" in choice.reason and "no bf16 units (amx_bf16/avx512_bf16)" in choice.reason


def test_flags_without_a_fast_probe_do_not_choose_bf16():
    """The probe decides (a PyTorch build without the units' kernels): flags alone do not."""
    assert choose_precision("auto", OMNET, SAME, Device("cpu", ("avx512_bf16",), bf16_speedup=0.9)).precision == FP32
    assert choose_precision("auto", OMNET, SAME, Device("cpu", ("avx512_bf16",))).precision == FP32


def test_auto_keeps_fp32_for_a_method_that_bf16_changes_or_that_is_not_measured():
    changed = choose_precision("auto", OMNET, CHANGES, AMX)
    assert changed == precision.PrecisionChoice(FP32, "bf16 changes OMNet's result (2x the error)")
    unmeasured = choose_precision("auto", "baselines.learned.dcp.DCP", SAME, AMX)
    assert unmeasured == precision.PrecisionChoice(FP32, "bf16's effect on DCP's result is not measured")


def test_auto_on_a_gpu_follows_its_bf16_support():
    assert choose_precision("auto", OMNET, SAME, Device("cuda", gpu_bf16=True)).precision == BF16
    assert choose_precision("auto", OMNET, SAME, Device("cuda", gpu_bf16=False)).precision == FP32
    assert choose_precision("auto", OMNET, CHANGES, Device("cuda", gpu_bf16=True)).precision == FP32


def test_an_explicit_precision_wins_with_what_is_known_about_it():
    assert choose_precision("32-true", OMNET, SAME, AMX) == precision.PrecisionChoice("32-true", "trainer.precision given")
    emulated = choose_precision("bf16-mixed", OMNET, SAME, ZEN2)
    assert emulated.precision == "bf16-mixed" and "bf16 is emulated and slower" in emulated.reason
    unmeasured = choose_precision("bf16-mixed", "baselines.learned.dcp.DCP", SAME, AMX)
    assert unmeasured.reason == "trainer.precision given; bf16's effect on DCP's result is not measured"


def test_explicit_bf16_for_a_method_it_changes_is_refused_unless_forced():
    with pytest.raises(ConfigError, match=r"^trainer.precision=bf16-mixed: bf16 changes OMNet's result \(2x the error\); "
                                          r"use trainer.precision=32-true \(or auto\), or force_precision=true"):
        choose_precision("bf16-mixed", OMNET, CHANGES, AMX)
    forced = choose_precision("bf16-mixed", OMNET, CHANGES, AMX, force=True)
    assert forced.precision == "bf16-mixed" and "forced: bf16 changes OMNet's result" in forced.reason


def test_settle_precision_writes_the_choice_into_the_config(monkeypatch):
    """On the run's config: probed only when bf16 is a candidate, the choice recorded in trainer.precision."""
    probes = []
    monkeypatch.setattr(precision, "load_verdicts", lambda: SAME)
    monkeypatch.setattr(precision, "read_cpu_flags", lambda: frozenset({"avx2"}))
    monkeypatch.setattr(precision, "probe_bf16_speedup", lambda: probes.append(1) or 0.02)
    cfg = OmegaConf.create({"trainer": {"precision": "auto", "accelerator": "cpu"}, "force_precision": False,
                            "model": {"network": {"_target_": OMNET}}})
    choice = settle_precision(cfg)
    assert (choice.precision, cfg.trainer.precision, len(probes)) == (FP32, FP32, 1)
    cfg.model.network._target_ = "baselines.learned.dcp.DCP"
    cfg.trainer.precision = "auto"
    assert run_precision(cfg).precision == FP32 and len(probes) == 1  # not measured: no probe needed


def test_the_probe_measures_a_rate_ratio():
    assert precision.probe_bf16_speedup(size=32, repeats=1) > 0


def test_every_verdict_names_a_network_of_a_model_config():
    targets = {OmegaConf.select(OmegaConf.load(p), "network._target_") for p in (ROOT / "conf" / "model").rglob("*.yaml")}
    assert set(load_verdicts()) <= targets
    with pytest.raises(ValueError, match="must be one of same, changes"):
        Verdict("worse", "")
