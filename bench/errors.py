"""Errors the command line tells apart from the user's mistakes (light: no imports, so that the command line
parses before it imports the simulation)."""


class SimulationDefectError(RuntimeError):
    """An error raised inside the closed loop that no check of the input foresaw (a ``ValueError``, an overflow,
    a type, lookup, attribute or assertion error).

    The scenario passed its checks and the world was built from it, so such an error is a defect of landbench
    (or of a library it calls), not the user's mistake: the command line reports it as an internal error with
    its traceback, not as a ``landbench: error:`` line about the input. A plug-in law's bad output or exception
    (:class:`gnc.plugins.LawOutputError`) and a scenario check made in flight (:class:`ScenarioError`) still
    are the user's, named with their field.
    """
