"""The run log (MCAP): :class:`RunLog` writes it as the run goes, :func:`read_run_log` reads it back."""
from .reader import DT, FORMAT, RESULTS, cut_short, read_metadata, read_run_log, results_of
from .writer import MAX_MESSAGE, MIN_FREE, RunLog

__all__ = ["DT", "FORMAT", "MAX_MESSAGE", "MIN_FREE", "RESULTS", "RunLog", "cut_short", "read_metadata", "read_run_log",
           "results_of"]
