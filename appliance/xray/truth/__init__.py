"""Ground truth for the X-ray renderer, apart from the product: closed-form line integrals of
boxes and ellipsoids (`analytic`) and a plain NumPy Siddon renderer (`reference`).

Used by the tests and by `fluorosim bench drr`, never by the appliance's frame path; they
share no code with the OpenCL kernels they check.
"""
