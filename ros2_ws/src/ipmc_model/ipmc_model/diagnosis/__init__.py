"""Residual diagnosis: which physical effect does a hysteresis model lack?

* :mod:`.record` - the record, its fit / held-out split and what its excitation can show;
* :mod:`.candidates` - one class per candidate effect and the registry :data:`CANDIDATES`;
* :mod:`.decision` - the one decision rule (Diebold-Mariano, Holm, materiality);
* :mod:`.search` - rounds of candidates around the current model;
* :mod:`.experiment` - the next experiment: an excitation that decides what was not testable;
* :mod:`.results` - typed evidence and outcomes; :mod:`.report` - files, deciding nothing;
* :mod:`.config` - every threshold, in one frozen object.
"""

from .candidates import CANDIDATES, Candidate, Fitted, register
from .config import DiagnosisConfig
from .experiment import Experiment, Probe, design_experiment
from .results import CandidateResult, Diagnosis, Outcome
from .search import diagnose

__all__ = ["CANDIDATES", "Candidate", "CandidateResult", "Diagnosis", "DiagnosisConfig",
           "Experiment", "Fitted", "Outcome", "Probe", "design_experiment", "diagnose",
           "register"]
