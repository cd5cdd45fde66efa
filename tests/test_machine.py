import torch

from kneas_method.engine.machine import describe, machine_record, processor_name


def test_the_processor_is_named_from_cpuinfo_or_platform(tmp_path):
    info = tmp_path / "cpuinfo"
    info.write_text("processor\t: 0\nvendor_id\t: X\nmodel name\t:  Example   CPU 9000 @ 3.0GHz\n\nprocessor\t: 1\nmodel name\t: Example CPU 9000 @ 3.0GHz\n")
    assert processor_name(info) == "Example CPU 9000 @ 3.0GHz"
    assert processor_name(tmp_path / "missing") not in ("", None)  # another OS: what platform knows


def test_a_cpu_run_records_processor_cores_and_torch():
    rec = machine_record("cpu")
    assert set(rec) == {"processor", "cores", "torch"} and rec["torch"] == torch.__version__ and rec["cores"] >= 1
    assert describe(rec) == f"{rec['processor']} / {rec['cores']} cores / torch {torch.__version__}"


def test_labels():
    assert describe(None) == describe({}) == "not recorded"
    assert describe({"processor": "P", "cores": 2, "torch": "2.11.0", "gpu": "NVIDIA H100"}) == "NVIDIA H100 / torch 2.11.0"
