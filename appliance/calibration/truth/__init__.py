"""Ground truth for the X-ray calibration, apart from the product: calibration sessions at a
known machine geometry (`scenario`), analytic images of the sphere phantom (`shadowgraph`)
and the phantom as a CT volume for the DRR renderer (`rendered_phantom`).

Used by the tests and by `fluorosim bench calibration`, never by `fluorosim calibrate`
itself; none of it shares code with blob detection or the fit.
"""
