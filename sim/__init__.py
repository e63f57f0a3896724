"""Batched two-mass plant, drive, measurement, test signal and records (SI units)."""

from sim.measurement import encoder_count, speed_from_angle
from sim.params import (ALL_PARAM_NAMES, CLASS_THRESHOLDS, DERIVED_NAMES, PARAM_NAMES, REAL_AXIS_NAMES, R_OSC_VISIBLE,
                        S_N_ELASTIC, S_N_STIFF_BACKLASH, STRUCTURE_CLASSES,
                        W_E_T_EI_STIFF, DriveConfig, TwoMassDerived, TwoMassParams, class_index, gap_width,
                        normalized_backlash, one_mass_stand_in, speed_quantum, structure_class, two_mass_derived)
from sim._config import load_c_kernel
from sim._integrate_fast import default_substeps, rk4_substeps
from sim.plant import Controller, Plant, Response, SimulatedPlant, simulate, simulate_test
from sim.population import (EnvelopeRanges, EnvelopeSample, PopulationRanges, RealAxisRanges, sample_envelope,
                            sample_population)
from sim.records import Record, RecordError, RecordMeta, iter_records, read_record, responses_to_records, write_record
from sim.replay import replay_speed
from sim._drive import Drive, DriveLimits, Scenario, SimulatedDrive, SpeedLaw, limit_violation
from sim._signal import (SECTION_LEVELS, SECTION_NAMES, SPEED_RETURN, SwitchingController, TestSignalConfig, inertia_of_time_scale,
                         time_scale)

__all__ = [
    "CLASS_THRESHOLDS", "STRUCTURE_CLASSES", "SECTION_NAMES", "SECTION_LEVELS", "SPEED_RETURN", "PARAM_NAMES", "DERIVED_NAMES",
    "REAL_AXIS_NAMES", "ALL_PARAM_NAMES", "RealAxisRanges",
    "TwoMassDerived", "two_mass_derived", "class_index", "gap_width", "normalized_backlash", "one_mass_stand_in",
    "speed_quantum", "S_N_ELASTIC", "S_N_STIFF_BACKLASH", "W_E_T_EI_STIFF",
    "R_OSC_VISIBLE", "Controller", "DriveConfig", "Plant", "PopulationRanges", "Record", "RecordMeta",
    "RecordError", "Response", "SimulatedPlant", "SwitchingController", "TestSignalConfig", "TwoMassParams",
    "default_substeps", "rk4_substeps", "load_c_kernel", "encoder_count", "iter_records", "read_record", "replay_speed",
    "responses_to_records", "sample_population", "simulate",
    "simulate_test", "speed_from_angle", "structure_class", "write_record",
    "Drive", "DriveLimits", "Scenario", "SimulatedDrive", "SpeedLaw", "limit_violation",
    "EnvelopeRanges", "EnvelopeSample", "sample_envelope", "time_scale", "inertia_of_time_scale",
]
