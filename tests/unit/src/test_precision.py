"""The run's precision: chosen from the verdict table's row for the method on the device kind (faked here), an
explicit one honoured or refused in one line, evaluation in float32, the CPU kinds of /proc/cpuinfo, the table
well formed."""

import pytest
import yaml
from omegaconf import OmegaConf

import src.run.precision as precision
from src.run.precision import (
    BF16,
    DEVICE_KINDS,
    FP32,
    Device,
    Outcome,
    PrecisionChoice,
    Spread,
    Verdict,
    bf16_verdict,
    choose_precision,
    cpu_flags,
    cpu_kind,
    cpu_model,
    load_verdicts,
    run_precision,
    settle_precision,
    switch_to_fp32,
)
from src.utils.errors import ConfigError
from tests.helpers.paths import ROOT

OMNET = "src.models.omnet.OMNet"
FP32_RUNS = Outcome(3, 900.0, 1800.0, Spread(14.0, 12.0, 16.0))


def _verdict(ttt: float | None, bf16_final: Spread, kind: str = "intel-amx") -> Verdict:
    """A row of OMNet on ``kind``: fp32 final 14.0 (12.0-16.0) deg; bf16 ``ttt``x as fast to the target."""
    bf16 = Outcome(3, 1000.0, None if ttt is None else 1800.0 / ttt, bf16_final)
    return Verdict(OMNET, kind, "Intel Xeon X", "real airplanes", 20.0, (0, 1, 2), 1.9, ttt, FP32_RUNS, bf16,
                   "python -m benchmarks.studies.precision.time_to_accuracy", bf16_verdict(ttt, FP32_RUNS.final_deg, bf16_final))


FASTER_SAME = _verdict(1.4, Spread(14.5, 13.0, 16.5))
SLOWER = _verdict(0.8, Spread(14.5, 13.0, 16.5))
WORSE = _verdict(1.4, Spread(26.6, 24.0, 29.0))
AMX = Device("cpu", "intel-amx", bf16_speedup=7.1)
ZEN3 = Device("cpu", "avx2-no-bf16", bf16_speedup=0.02)

XEON = ("processor\t: 0\nvendor_id\t: GenuineIntel\nmodel name\t: Intel(R) Xeon(R) Platinum 8480+\n"
        "flags\t\t: fpu avx2 avx512_bf16 amx_bf16\n")
ZEN4 = "processor\t: 0\nvendor_id\t: AuthenticAMD\nmodel name\t: AMD EPYC 9654\nflags\t\t: fpu avx2 avx512f avx512_bf16\n"
ZEN2 = "processor\t: 0\nvendor_id\t: AuthenticAMD\nmodel name\t: AMD EPYC 7B12\nflags\t\t: fpu avx2\n"
GRAVITON3 = "processor\t: 0\nFeatures\t: fp asimd sve bf16\nCPU implementer\t: 0x41\n"


def test_cpu_flags_are_read_from_cpuinfo_text():
    text = "processor\t: 0\nvendor_id\t: AuthenticAMD\nflags\t\t: fpu avx2 amx_bf16 sse\n\nprocessor\t: 1\nflags\t: fpu\n"
    assert cpu_flags(text) == {"fpu", "avx2", "amx_bf16", "sse"}
    assert cpu_flags("Features\t: fp asimd bf16\n") == {"fp", "asimd", "bf16"}
    assert cpu_flags("no flags here") == frozenset()


@pytest.mark.parametrize("cpuinfo, kind", [(XEON, "intel-amx"), (ZEN4, "amd-avx512bf16"), (ZEN2, "avx2-no-bf16"),
                                           (GRAVITON3, "arm-bf16"), ("", "other-no-bf16")])
def test_cpu_kinds_are_the_vendor_and_its_fastest_bf16_unit(cpuinfo, kind):
    assert cpu_kind(cpuinfo) == kind and kind in DEVICE_KINDS


def test_cpu_model_names_the_cpu():
    assert (cpu_model(XEON), cpu_model(GRAVITON3)) == ("Intel(R) Xeon(R) Platinum 8480+", "unknown CPU")


def test_the_verdict_takes_bf16_only_when_faster_to_the_target_and_within_the_fp32_spread():
    fp32 = FP32_RUNS.final_deg
    assert bf16_verdict(1.4, fp32, Spread(14.5, 13.0, 16.5)) == "bf16"
    assert bf16_verdict(0.8, fp32, Spread(14.5, 13.0, 16.5)) == "fp32"  # slower to the target
    assert bf16_verdict(None, fp32, Spread(14.5, 13.0, 16.5)) == "fp32"  # a seed never reached it
    assert bf16_verdict(1.4, fp32, Spread(26.6, 24.0, 29.0)) == "fp32"  # worse than every fp32 seed
    assert bf16_verdict(1.4, fp32, Spread(11.0, 10.0, 12.0)) == "fp32"  # outside the spread either way


def test_auto_takes_bf16_where_the_kinds_verdict_says_so_and_names_it():
    choice = choose_precision("auto", OMNET, {(OMNET, "intel-amx"): FASTER_SAME}, AMX)
    assert choice.precision == BF16
    assert choice.reason.startswith("verdict for OMNet on intel-amx (src/run/precision_verdicts.yaml): bf16 (bf16 "
                                    "reached 20 deg 1.4x as fast in CPU time, steps 1.9x as fast")
    assert choice.reason.endswith("3 seeds; measured on Intel Xeon X)")
    assert "final Error(R) bf16 14.5 (13.0-16.5) deg, fp32 14.0 (12.0-16.0) deg, 3 seeds" in choice.reason


@pytest.mark.parametrize("verdict", [SLOWER, WORSE, _verdict(None, Spread(14.5, 13.0, 16.5))])
def test_auto_keeps_fp32_where_the_kinds_verdict_says_fp32(verdict):
    choice = choose_precision("auto", OMNET, {(OMNET, "intel-amx"): verdict}, AMX)
    assert choice.precision == FP32 and choice.reason.startswith(
        "verdict for OMNet on intel-amx (src/run/precision_verdicts.yaml): fp32 (")


def test_without_a_measured_verdict_for_the_method_on_this_kind_auto_keeps_fp32():
    """Another kind's bf16 verdict (another CPU), another method's: neither is this one's."""
    verdicts = {(OMNET, "intel-amx"): FASTER_SAME}
    zen4 = Device("cpu", "amd-avx512bf16", bf16_speedup=3.0)
    assert choose_precision("auto", OMNET, verdicts, zen4) == PrecisionChoice(
        FP32, "no measured verdict for OMNet on amd-avx512bf16: fp32")
    assert choose_precision("auto", "baselines.learned.dcp.DCP", verdicts, AMX) == PrecisionChoice(
        FP32, "no measured verdict for DCP on intel-amx: fp32")
    assert choose_precision("auto", OMNET, {}, Device("cuda", "gpu-bf16")).reason == (
        "no measured verdict for OMNet on gpu-bf16: fp32")


def test_a_bf16_verdict_on_a_cpu_whose_bf16_products_are_not_fast_keeps_fp32():
    """The probe guards a row: a PyTorch build without the units' kernels emulates bf16."""
    choice = choose_precision("auto", OMNET, {(OMNET, "intel-amx"): FASTER_SAME}, Device("cpu", "intel-amx", bf16_speedup=0.9))
    assert choice.precision == FP32 and choice.reason.endswith(
        "but bf16 matrix products run 0.9x the float32 rate on this CPU (intel-amx): fp32")


def test_an_explicit_precision_wins_with_what_is_known_about_it():
    verdicts = {(OMNET, "intel-amx"): FASTER_SAME}
    assert choose_precision("32-true", OMNET, verdicts, AMX) == PrecisionChoice("32-true", "trainer.precision given")
    emulated = choose_precision("bf16-mixed", OMNET, verdicts, ZEN3)
    assert emulated == PrecisionChoice("bf16-mixed", "trainer.precision given; no measured verdict for OMNet on avx2-no-bf16; "
                                       "bf16 matrix products run 0.02x the float32 rate on this CPU (avx2-no-bf16)")
    measured = choose_precision("bf16-mixed", OMNET, {(OMNET, "intel-amx"): SLOWER}, AMX)
    assert measured.precision == "bf16-mixed"
    assert "verdict for OMNet on intel-amx (src/run/precision_verdicts.yaml): fp32 (" in measured.reason


def test_explicit_bf16_where_it_moves_the_final_error_outside_the_fp32_spread_is_refused_unless_forced():
    verdicts = {(OMNET, "intel-amx"): WORSE}
    with pytest.raises(ConfigError, match=r"^trainer.precision=bf16-mixed: bf16 moves OMNet's final error outside "
                                          r"float32's seed spread on intel-amx \(src/run/precision_verdicts.yaml\) "
                                          r"\(.*\); use trainer.precision=32-true "
                                          r"\(or auto\), or force_precision=true"):
        choose_precision("bf16-mixed", OMNET, verdicts, AMX)
    forced = choose_precision("bf16-mixed", OMNET, verdicts, AMX, force=True)
    assert forced.precision == "bf16-mixed" and "forced: bf16 moves OMNet's final error" in forced.reason


def _cfg(requested: str) -> OmegaConf:
    return OmegaConf.create({"trainer": {"precision": requested, "accelerator": "cpu"}, "force_precision": False,
                             "model": {"network": {"_target_": OMNET}}})


def test_settle_precision_writes_the_choice_into_the_config(monkeypatch):
    """On the run's config: the CPU probed only where bf16 is a candidate, the choice recorded in trainer.precision."""
    probes = []
    monkeypatch.setattr(precision, "load_verdicts", lambda: {(OMNET, "intel-amx"): FASTER_SAME})
    monkeypatch.setattr(precision, "read_cpuinfo", lambda: XEON)
    monkeypatch.setattr(precision, "probe_bf16_speedup", lambda: probes.append(1) or 7.1)
    cfg = _cfg("auto")
    choice = settle_precision(cfg)
    assert (choice.precision, cfg.trainer.precision, len(probes)) == (BF16, BF16, 1)
    monkeypatch.setattr(precision, "read_cpuinfo", lambda: ZEN4)
    assert run_precision(_cfg("auto")).precision == FP32 and len(probes) == 1  # no verdict on this kind: no probe


def test_evaluation_runs_in_float32_unless_a_precision_is_given(monkeypatch):
    """Even where training would take bf16: a checkpoint's numbers are its weights'."""
    monkeypatch.setattr(precision, "load_verdicts", lambda: {(OMNET, "intel-amx"): FASTER_SAME})
    monkeypatch.setattr(precision, "read_cpuinfo", lambda: XEON)
    monkeypatch.setattr(precision, "probe_bf16_speedup", lambda: 7.1)
    cfg = _cfg("auto")
    assert settle_precision(cfg, evaluation=True) == PrecisionChoice(FP32, precision.EVALUATED_IN_FP32)
    assert cfg.trainer.precision == FP32
    asked = _cfg("bf16-mixed")
    assert settle_precision(asked, evaluation=True).precision == "bf16-mixed" == asked.trainer.precision


def test_the_probe_measures_a_rate_ratio():
    assert precision.probe_bf16_speedup(size=32, repeats=1) > 0


def test_a_row_round_trips_and_its_verdict_must_follow_its_numbers(tmp_path):
    assert Verdict.from_record(yaml.safe_load(yaml.safe_dump(FASTER_SAME.record()))) == FASTER_SAME
    record = FASTER_SAME.record()
    with pytest.raises(ValueError, match="verdict 'bf16', but its numbers give 'fp32'"):
        Verdict.from_record(record | {"time_to_target_speedup": 0.9})
    with pytest.raises(ValueError, match="2 seeds, at least 3 needed"):
        Verdict.from_record(record | {"seeds": [0, 1]})
    with pytest.raises(ValueError, match="unknown device kind"):
        Verdict.from_record(record | {"cpu_kind": "zen4"})
    table = tmp_path / "verdicts.yaml"
    table.write_text(yaml.safe_dump([record, record]))
    with pytest.raises(ValueError, match="two verdicts for src.models.omnet.OMNet on intel-amx"):
        load_verdicts.__wrapped__(table)


def test_the_verdict_table_is_well_formed_and_names_networks_of_model_configs():
    targets = {OmegaConf.select(OmegaConf.load(p), "network._target_") for p in (ROOT / "conf" / "model").rglob("*.yaml")}
    assert {method for method, _ in load_verdicts()} <= targets


@pytest.mark.parametrize("trained", ["bf16-mixed", "bf16-true", "32-true", "64-true"])
def test_a_trainer_that_trained_in_bf16_tests_in_float32(trained):
    import lightning as L
    import torch

    trainer = L.Trainer(accelerator="cpu", precision=trained, logger=False, enable_checkpointing=False,
                        enable_progress_bar=False, enable_model_summary=False)
    module = torch.nn.Linear(2, 2).to(torch.bfloat16 if trained == "bf16-true" else torch.float32)
    switch_to_fp32(trainer, module)
    assert trainer.precision == ("64-true" if trained == "64-true" else FP32)
    assert module.weight.dtype == torch.float32
