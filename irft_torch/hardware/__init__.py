"""Sensing only: motor model, five-bar leg statics, the CAN bus's frames and logs (``bus``: ODrive CANSimple and
CubeMars/T-Motor AK MIT mode), the paper's signal pipeline, a simulated leg on a virtual bus, and the live path
(``live``: frames in, an updated terrain estimate out after every stance). Imports neither ``gp`` nor plotting."""

from .air_baseline import AirBaseline
from .bus.can_log import SUPPORTED_SUFFIXES, read_log, record
from .bus.log_data import LogData, LogReadError, MotorSeries, ResampledLog
from .bus.mit_can import MIT_ERRORS, MIT_MODELS, MitModel, decode_mit, encode_mit_reply, mit_model
from .bus.odrive_can import COMMANDS, Frame, FrameError, arbitration_id, decode, encode, request, split_id
from .five_bar import FiveBarLeg, SingularConfigurationWarning
from .live import LiveEstimate, LiveEstimator
from .live.causal_filter import CausalMovingAverage
from .live.resample import LiveResampler
from .live.stance import Stance, StanceDetector
from .motor import MotorModel, kt_from_kv
from .pipeline import (
                       Dataset,
                       ForceTrace,
                       average_trials,
                       build_dataset,
                       dataset_summary,
                       forces_from_log,
                       load_dataset,
                       save_dataset,
                       subtract_air,
                       zero_phase_filter,
)
from .simulated_leg import FakeODrive, SimulatedLeg, SimulationTruth
from .walking_leg import WalkingLeg, stride_path

__all__ = [
    "MotorModel", "kt_from_kv", "FiveBarLeg", "SingularConfigurationWarning",
    "COMMANDS", "Frame", "FrameError", "arbitration_id", "split_id", "encode", "decode", "request",
    "MitModel", "MIT_MODELS", "MIT_ERRORS", "decode_mit", "encode_mit_reply", "mit_model",
    "SUPPORTED_SUFFIXES", "MotorSeries", "LogData", "ResampledLog", "LogReadError", "read_log", "record",
    "ForceTrace", "forces_from_log", "subtract_air", "zero_phase_filter", "average_trials",
    "Dataset", "build_dataset", "dataset_summary", "save_dataset", "load_dataset",
    "FakeODrive", "SimulatedLeg", "SimulationTruth",
    "LiveEstimator", "LiveEstimate", "LiveResampler", "AirBaseline", "CausalMovingAverage", "Stance", "StanceDetector",
    "WalkingLeg", "stride_path",
]
