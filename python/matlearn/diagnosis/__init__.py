"""Diagnosis of the sim-to-real gap (method.md section 9): where the nominal model is wrong,
which unmodelled effect explains it, and how far the held-out gap shrinks once it is added.

    from matlearn.diagnosis import diagnose
    result = diagnose("scene.toml", "out/")   # writes out/diagnosis.json, report.html, *.vtu
"""
from .effects import CANDIDATES, FAMILIES, VOCABULARY, EffectContext, build_model
from .pipeline import diagnose

__all__ = ["diagnose", "VOCABULARY", "FAMILIES", "CANDIDATES", "EffectContext", "build_model"]
