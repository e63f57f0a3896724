"""Batched two-mass plant, drive, measurement, test signal and records (SI units)."""

from sim.measurement import encoder_count, speed_from_angle
from sim.params import STRUCTURE_CLASSES, DriveConfig, TwoMassParams, structure_class
from sim.plant import Controller, Plant, Response, SimulatedPlant, simulate, simulate_test
from sim.population import PopulationRanges, sample_population
from sim.records import Record, RecordError, iter_records, read_record, responses_to_records, write_record
from sim.replay import replay_speed
from sim.test_signal import SECTION_NAMES, SwitchingController, TestSignalConfig

__all__ = [
    "STRUCTURE_CLASSES", "SECTION_NAMES", "Controller", "DriveConfig", "Plant", "PopulationRanges", "Record",
    "RecordError", "Response", "SimulatedPlant", "SwitchingController", "TestSignalConfig", "TwoMassParams",
    "encoder_count", "iter_records", "read_record", "replay_speed", "responses_to_records", "sample_population", "simulate",
    "simulate_test", "speed_from_angle", "structure_class", "write_record",
]
