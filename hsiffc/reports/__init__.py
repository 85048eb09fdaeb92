"""Reports that compare calibrated models with measured data (figures, tables, JSON summaries).

* :mod:`hsiffc.reports.emva_leakage` -- linear model (paper eq. 1) against the leakage model on
  a real EMVA 1288 exposure sweep: RMS errors, pixels that level off below full scale, fitted
  dynamic saturation levels against the plateaus the pixels reach.
"""
