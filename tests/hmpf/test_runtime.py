"""hmpf.runtime's description of the machine a figure was measured on."""

from __future__ import annotations

import platform

from hmpf.runtime import machine_description, vector_extensions


def test_vector_extensions_names_the_widest() -> None:
    assert vector_extensions({"fma", "avx", "avx2", "sha_ni"}) == "AVX2"
    assert vector_extensions({"avx2", "avx512f", "avx512bw"}) == "AVX-512"
    assert vector_extensions({"avx2", "avx512f", "avx512_bf16"}) == "AVX-512 BF16"
    assert vector_extensions({"avx512f", "avx512_bf16", "amx_tile", "amx_bf16"}) == "AMX"
    assert vector_extensions({"sse4_2"}) is None


def test_machine_description_keeps_its_three_parts() -> None:
    text = machine_description()
    cpu, cores, python = text.split(", ")
    assert cpu and cores.endswith(" cores") and python == f"Python {platform.python_version()}"
