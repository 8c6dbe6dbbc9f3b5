"""Modal model, parameter intervals, frequency data, prior, weights and the experiment protocol (thesis chapter 2)."""

from setmem_hil.model.modal_model import ModalParameters, IntervalModel, PARAM_NAMES
from setmem_hil.model.frequency_data import FrequencyData
from setmem_hil.model.prior import ModePrior, Prior
from setmem_hil.model.weights import Weights, THESIS_WEIGHTS
from setmem_hil.model.experiment import Experiment, Measurement

__all__ = ["Experiment", "FrequencyData", "IntervalModel", "Measurement", "ModalParameters", "ModePrior", "PARAM_NAMES", "Prior", "THESIS_WEIGHTS", "Weights"]
