"""The machine description recorded with every result: read from /proc/cpuinfo, recorded but never keyed."""

from mftcn_bench.core import identity, provenance
from mftcn_bench.core.provenance import cpu_model, versions

X86_CPUINFO = """processor\t: 0
vendor_id\t: AuthenticAMD
cpu family\t: 23
model\t\t: 1
model name\t: AMD EPYC 7551 32-Core Processor
flags\t\t: fpu sse sse2 sse4_2 avx fma avx2 sha_ni

processor\t: 1
vendor_id\t: AuthenticAMD
cpu family\t: 23
model\t\t: 1
model name\t: AMD EPYC 7551 32-Core Processor
flags\t\t: fpu sse sse2 sse4_2 avx fma avx2 sha_ni
"""

ARM_CPUINFO = """processor\t: 0
BogoMIPS\t: 243.75
Features\t: fp asimd evtstrm aes pmull sha1 sha2 crc32 atomics sve
CPU implementer\t: 0x41
"""


def test_x86_cpu_names_model_family_and_the_vector_extensions_that_pick_kernels():
    assert cpu_model(X86_CPUINFO) == "AMD EPYC 7551 32-Core Processor (family 23, model 1; avx2 fma)"


def test_avx512_shows_so_two_epyc_generations_read_apart():
    zen4 = X86_CPUINFO.replace("model\t\t: 1", "model\t\t: 17").replace("avx2", "avx2 avx512f")
    assert cpu_model(zen4).endswith("(family 23, model 17; avx512f avx2 fma)")


def test_cpu_without_a_model_name_falls_back_to_the_platform(monkeypatch):
    monkeypatch.setattr(provenance.platform, "processor", lambda: "")
    monkeypatch.setattr(provenance.platform, "machine", lambda: "aarch64")
    assert cpu_model(ARM_CPUINFO) == "aarch64 (asimd sve)"
    assert cpu_model("") == "aarch64"


def test_the_cpu_is_recorded_with_results_but_keys_nothing():
    recorded = versions()
    assert recorded["cpu"]
    assert "cpu" not in identity.library_versions()
