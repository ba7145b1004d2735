"""Offline processing of run files: HDR merge, trace, fit, light model, exports, report.

It reads run files through :mod:`drivers.contracts.runfile` and never talks to hardware.
"""
