import numpy as np
import pyopencl as cl
import tifffile
import pytest

from cm2cl import device
from cm2cl.device import runtime
from cm2cl.cli import main
from cm2cl.errors import DeviceError


def test_list_devices_records_capabilities(rt):
    caps = device.list_devices()
    assert caps, "at least the device of the rt fixture"
    for c in caps:
        assert c.global_mem > 0 and 0 < c.max_alloc <= c.global_mem
        assert c.max_work_group_size >= 1 and c.compute_units >= 1
        assert isinstance(c.fp64, bool)


def test_select_by_index_env(rt, monkeypatch):
    caps = device.list_devices()
    last = caps[-1]
    monkeypatch.setenv("CM2CL_DEVICE", str(last.index))
    d = device.select_device()
    assert d.name.strip() == last.name and d.platform.name.strip() == last.platform


def test_select_by_name_fragment_env(rt, monkeypatch):
    c = device.list_devices()[0]
    frag = c.name.split()[0][-6:].upper()  # a case-insensitive fragment of the name
    monkeypatch.setenv("CM2CL_DEVICE", frag)
    assert frag.lower() in device.select_device().name.lower()


def test_env_overrides_pyopencl_ctx(rt, monkeypatch):
    caps = device.list_devices()
    monkeypatch.setenv("PYOPENCL_CTX", "0:0")
    monkeypatch.setenv("CM2CL_DEVICE", str(caps[-1].index))
    assert device.select_device().name.strip() == caps[-1].name
    monkeypatch.delenv("CM2CL_DEVICE")
    first = cl.get_platforms()[0].get_devices()[0]
    assert device.select_device().int_ptr == first.int_ptr


def test_unknown_name_is_a_clear_error(rt, monkeypatch):
    monkeypatch.setenv("CM2CL_DEVICE", "no-such-gpu-xyz")
    with pytest.raises(DeviceError, match=r"CM2CL_DEVICE='no-such-gpu-xyz': no OpenCL device name matches"):
        device.select_device()


def test_index_out_of_range_is_a_clear_error(rt, monkeypatch):
    monkeypatch.setenv("CM2CL_DEVICE", "99")
    with pytest.raises(DeviceError, match="out of range"):
        device.select_device()


def test_no_device_message_says_how_to_get_pocl(monkeypatch, capsys):
    monkeypatch.setattr(runtime, "_all_devices", lambda: ())
    monkeypatch.delenv("CM2CL_DEVICE", raising=False)
    monkeypatch.delenv("PYOPENCL_CTX", raising=False)
    with pytest.raises(DeviceError, match="PoCL"):
        device.select_device()
    assert main(["devices"]) != 0
    err = capsys.readouterr().err
    assert "pocl" in err.lower() and "Traceback" not in err


def test_scoring_prefers_gpus():
    base = dict(index=0, name="x", platform="p", fp64=True, global_mem=2**30, max_alloc=2**28,
                max_work_group_size=256, compute_units=4, local_mem=2**15, opencl_version="3.0")
    cpu = device.Capabilities(**{**base, "kind": "CPU", "global_mem": 64 * 2**30, "compute_units": 64})
    gpu = device.Capabilities(**{**base, "kind": "GPU"})
    assert gpu.score > cpu.score


def test_device_table_prints_whole_names():
    """A long name (PoCL's CPU names run past 40 characters) is printed whole, so that the fragment a
    user copies from the table selects the device."""
    name = "pthread-skylake-avx512-Intel(R) Xeon(R) Processor @ 2.10GHz"
    caps = device.Capabilities(index=3, name=name, platform="p", kind="CPU", fp64=True, global_mem=2**30,
                               max_alloc=2**28, max_work_group_size=256, compute_units=4, local_mem=2**15,
                               opencl_version="3.0")
    rows = runtime.format_table([caps], chosen=3).splitlines()
    assert len(rows) == 3 and rows[2].startswith("*3") and name in rows[2]


def test_devices_command_prints_table(rt, capsys):
    assert main(["devices"]) == 0
    out = capsys.readouterr().out
    assert "fp64" in out and "max buffer" in out and rt.caps.name in out


def test_float64_refused_without_fp64(rt):
    import numpy as np

    fake = device.Runtime.__new__(device.Runtime)
    fake.caps = device.Capabilities(**{**rt.caps.__dict__, "fp64": False})
    with pytest.raises(DeviceError, match="no fp64 support"):
        fake.check_dtype(np.float64)


def test_auto_choice_skips_devices_whose_compiler_fails(rt, monkeypatch):
    monkeypatch.delenv("CM2CL_DEVICE", raising=False)
    monkeypatch.delenv("PYOPENCL_CTX", raising=False)
    best = device.select_device()
    assert device.compiler_works(best)[0]
    broken = {best.int_ptr}
    monkeypatch.setattr(runtime, "compiler_works",
                        lambda d: (False, "error: unknown target CPU 'generic'") if d.int_ptr in broken else (True, ""))
    if len(runtime._all_devices()) > 1:
        assert device.select_device().int_ptr != best.int_ptr
    broken.update(d.int_ptr for d in runtime._all_devices())
    with pytest.raises(DeviceError, match=r"no OpenCL device can compile kernels: .*unknown target CPU 'generic'.*pocl-opencl-icd"):
        device.select_device()


def test_a_device_whose_compiler_fails_is_reported(rt, monkeypatch, capsys):
    """A device whose compiler cannot build the probe kernel is reported with the compiler's error
    line, both by compiler_works and in the `cm2cl devices` table (PyPI's PoCL 3.0 on CPUs that its
    LLVM 14 does not know fails like this)."""
    log = "Build on <pyopencl.Device 'x'>:\n\nerror: unknown target CPU 'generic'\n(options: -I ...)"

    class BrokenProgram:
        def __init__(self, *a, **k):
            pass

        def build(self, *a, **k):
            raise cl.RuntimeError(f"clBuildProgram failed: BUILD_PROGRAM_FAILURE - {log}")

    monkeypatch.setattr(runtime, "_PROBES", {})
    monkeypatch.setattr(cl, "Program", BrokenProgram)
    ok, why = device.compiler_works(runtime._all_devices()[0])
    assert not ok and why == "error: unknown target CPU 'generic'"
    monkeypatch.delenv("CM2CL_DEVICE", raising=False)
    monkeypatch.delenv("PYOPENCL_CTX", raising=False)
    assert main(["devices"]) == 2      # no device can compile: the table, then a one-line error
    cap = capsys.readouterr()
    assert "NO: error: unknown target CPU 'generic'" in cap.out
    assert "no OpenCL device can compile kernels" in cap.err and "Traceback" not in cap.err


def test_devices_table_names_the_implementation(rt, capsys):
    """`cm2cl devices` says which OpenCL implementation (and for PoCL which install) each device is."""
    assert main(["devices"]) == 0
    out = capsys.readouterr().out
    assert rt.caps.implementation[:40] in out
    assert runtime.implementation_of("Portable Computing Language", "OpenCL 3.0 PoCL 3.1+debian  Linux", "3.1") \
        == "PoCL 3.1+debian (system package)"
    assert runtime.implementation_of("NVIDIA CUDA", "OpenCL 3.0 CUDA 12.4.131", "550.54") == "NVIDIA CUDA (driver 550.54)"


def test_a_build_failure_is_one_line_with_the_log_in_a_file(rt, tmp_path, capsys, monkeypatch):
    """Issue 27: a device that cannot compile printed its 9-line build log; now the command prints one line
    (what failed where, the log's first error, where the whole log is) and exits 2."""
    import pyopencl as cl

    import cm2cl.solver
    from cm2cl.cli import main
    from cm2cl.device import kernels
    from cm2cl.errors import KernelBuildError
    from test_admm import bead_problem

    log = ("Build on <pyopencl.Device 'cpu-znver5'>:\n\nwarning: unknown target CPU\n"
           "error: unable to create target: 'No available targets are compatible with triple'\n"
           "error: second\n\n(options: -I ...)")

    class Broken:
        def __init__(self, *a, **k):
            pass

        def build(self, options=None):
            raise cl.RuntimeError(f"clBuildProgram failed: BUILD_PROGRAM_FAILURE - {log}")

    monkeypatch.setattr(cl, "Program", Broken)
    with pytest.raises(KernelBuildError) as info:
        kernels.program(rt, "splits.cl", np.float32, {"CM2CL_TEST_UNCACHED": 1})
    exc = info.value
    assert "\n" not in exc.summary and "unable to create target" in exc.summary and "kernels/splits.cl" in exc.summary
    assert "error: second" in exc.log
    monkeypatch.undo()
    monkeypatch.setattr(cm2cl.solver, "reconstruct", lambda *a, **k: (_ for _ in ()).throw(exc))
    psf, _, y = bead_problem(6)
    tifffile.imwrite(tmp_path / "psf.tif", psf.astype(np.float32), photometric="minisblack")
    tifffile.imwrite(tmp_path / "meas.tif", (y * 1000).astype(np.float32))
    code = main(["reconstruct", str(tmp_path / "meas.tif"), "--psf", str(tmp_path / "psf.tif"), "-o",
                 str(tmp_path / "v.ome.tif"), "--quiet"])
    err = capsys.readouterr().err
    assert code == 2 and len(err.strip().splitlines()) == 1 and "unable to create target" in err, err
    path = err.split("full build log: ")[1].split(";")[0]
    assert "error: second" in open(path).read() and not (tmp_path / "v.ome.tif").exists()
