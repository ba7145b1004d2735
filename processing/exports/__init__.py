"""Exports of a light model to the formats lighting software reads.

- :func:`write_ies` — IES LM-63-2019 photometric file, type C photometry: the **far field**
  of the whole light, ``Σ_s I_s(θ, φ)``.
- :func:`write_ldt` — EULUMDAT (``.ldt``), the same far field in cd/klm.
- :func:`write_tm25` / :func:`read_tm25` — IES TM-25-13 binary ray files: the **near
  field**, rays leaving each source's emitting disc with directions drawn from its own
  ``I_s(θ, φ)``.
- :func:`write_pbrt_lights` — the near field for renderers: each source a pbrt-v4
  ``goniometric`` light at its place, with its own equal-area intensity table.

Angles (both far-field formats): the light's axis (+z of the light frame) is photometric
nadir, vertical angle γ = θ; horizontal angle C = 0 is the light frame's +x, and C grows
counter-clockwise seen from above the luminaire hanging light-down (LM-63, type C), which
is towards the light's −y: ``C = (360° − φ) mod 360°``. The luminous opening's length runs
along C0–C180 (light x), its width along C90–C270 (light y).

Units: a light model is relative unless its run was calibrated, and even then it is
radiometric (W/sr). A far-field file therefore holds **relative intensities** unless a
``calibration`` factor (candela per model unit) is given; the file says which in its
keywords. Relative files follow the formats' relative photometry: intensities scaled to a
peak of 1000, with the lamp flux set to the flux of that same table (or to ``lamp_lumens``
when given, the intensities then scaled so the table carries exactly that flux).

Facts of the formats relied on (``docs/light-model.md`` cites them):
LM-63-2019 line 1 ``IES:LM-63-2019``, keywords ``[TEST] [TESTLAB] [ISSUEDATE] [MANUFAC]``
required, ``TILT=NONE``, then ``#lamps lumens/lamp multiplier #vertical #horizontal
photometric-type(1 = C) units-type(2 = metres) width length height``, then ``ballast-factor
file-generation-type input-watts``; the file generation type is a Table 2 token
(``1.00000`` test at an unaccredited lab, ``1.01000`` … with interpolated angle set,
``1.01100`` … interpolated and lumen scaled, ``1.00010`` computer simulation, ``1.00001``
undefined); lumens/lamp ``-1`` means absolute photometry. TM-25-13: little-endian, "TM25",
i32 2013, fluxes f32 at 12 and 16, u64 ray count at 20, eight i32 column flags at 256, nine
4000-byte UTF-32LE text fields from 288, spectral tables from 36288 zero-padded to a
multiple of 32 bytes, then 512-byte column labels and the additional text, then the rays
as float32 rows ``x y z kx ky kz`` (mm, unit vector) followed by the flagged columns.

Modules: :mod:`~processing.exports.far_field` (what the two far-field formats share),
:mod:`~processing.exports.ies`, :mod:`~processing.exports.ldt`,
:mod:`~processing.exports.tm25` and :mod:`~processing.exports.pbrt`.
"""

from processing.exports.far_field import ExportError
from processing.exports.ies import FILE_GENERATION_TYPES, write_ies
from processing.exports.ldt import write_ldt
from processing.exports.pbrt import write_pbrt_lights
from processing.exports.tm25 import TM25_COLUMNS, TM25Error, read_tm25, write_tm25

__all__ = [
    "ExportError",
    "FILE_GENERATION_TYPES",
    "TM25Error",
    "TM25_COLUMNS",
    "read_tm25",
    "write_ies",
    "write_ldt",
    "write_pbrt_lights",
    "write_tm25",
]
