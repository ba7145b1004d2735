"""Offline processing of run files: HDR merge, trace, fit, light model, exports, report.

It reads run files through the acquisition's run-file module and never talks to hardware.
"""
