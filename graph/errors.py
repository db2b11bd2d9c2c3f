"""Errors of the graph package."""


class SolverError(Exception):
    """iSAM2 rejected an update (e.g. an indeterminant system); the graph is as before it. Count and carry on."""
