"""The ``machine`` entry of every benchmark JSON (``benchmarks.machine``): CPU model, core count, load and the peaks
measured in the same process."""

import math

from hipolicy_jax import jsonio
from benchmarks import machine
from benchmarks.common import write_results


def test_cpu_model_reads_the_first_model_name(tmp_path):
    info = tmp_path / "cpuinfo"
    info.write_text("processor\t: 0\nvendor_id\t: GenuineIntel\nmodel name\t: Intel(R) Xeon(R) CPU @ 2.20GHz\n\n"
                    "processor\t: 1\nmodel name\t: something else\n")
    assert machine.cpu_model(str(info)) == "Intel(R) Xeon(R) CPU @ 2.20GHz"
    assert machine._model_name("vendor_id : x\n") is None
    assert isinstance(machine.cpu_model(str(tmp_path / "missing")), str)  # lscpu or 'unknown'


def test_machine_info_with_and_without_peaks(monkeypatch):
    info = machine.machine_info(lambda: {"matmul_f32_gflops": 1.0})
    assert info["peaks"] == {"matmul_f32_gflops": 1.0} and info["cpu_count"] >= 1 and info["cpu_model"]
    assert info["cpu_affinity"] is None or 1 <= info["cpu_affinity"] <= info["cpu_count"]
    assert info["load_average"] is None or len(info["load_average"]) == 3
    assert machine.machine_info()["peaks"] is None  # nothing to measure them with
    monkeypatch.setenv(machine.PEAKS_ENV, "0")
    assert machine.machine_info(lambda: {"matmul_f32_gflops": 1.0})["peaks"] is None


def test_every_benchmark_json_records_the_machine_and_its_measured_peaks(tmp_path, monkeypatch):
    monkeypatch.delenv(machine.PEAKS_ENV, raising=False)
    path = write_results("probe", {"rows": []}, str(tmp_path))
    res = jsonio.load(path)
    m = res["machine"]
    assert m["cpu_model"] == machine.cpu_model() and m["cpu_count"] >= 1
    for k in ("matmul_f32_gflops", "bandwidth_gbs"):
        assert isinstance(m["peaks"][k], float) and math.isfinite(m["peaks"][k]) and m["peaks"][k] > 0
    # figures measured earlier in the process are written as given
    assert jsonio.load(write_results("probe2", {}, str(tmp_path), peaks=m["peaks"]))["machine"]["peaks"] == m["peaks"]
