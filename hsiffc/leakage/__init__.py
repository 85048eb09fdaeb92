"""The leakage maths of the paper: the model ``dY/dt = k - a e^{bY}``, its closed-form
response and inversion (:mod:`.model`), the leakage percentage alpha and the validity flags
(:mod:`.validity`), and linearisation of responses (:mod:`.linearise`).
"""
