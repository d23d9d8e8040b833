"""``steerlab diagnose``: what the simulation gets wrong on measured data, which mechanism
explains it, the extended model, and what it gains. See docs/diagnosis.md.

Public API: :func:`run_diagnosis` (returns a :class:`DiagnosisResult`), :class:`DiagnosisError`
(bad input, a ``DataFileError``), and :data:`CANDIDATE_NAMES`.
"""

from steerlab.analysis.diagnosis.candidates import ALL_NAMES, CANDIDATE_NAMES
from steerlab.analysis.diagnosis.data import DiagnosisError
from steerlab.analysis.diagnosis.run import DiagnosisResult, run_diagnosis

__all__ = [
    "ALL_NAMES",
    "CANDIDATE_NAMES",
    "DiagnosisError",
    "DiagnosisResult",
    "run_diagnosis",
]
