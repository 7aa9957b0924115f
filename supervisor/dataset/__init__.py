"""Recorded datasets: the on-disk format, generation in simulation, benchmark suites."""

from supervisor.dataset.format import (
    FORMAT_VERSION,
    Dataset,
    DatasetWriter,
    FrameRecord,
)

__all__ = ["FORMAT_VERSION", "Dataset", "DatasetWriter", "FrameRecord"]
