"""Training: a fold's data (data.py), the Lightning module (module.py), fit and predict (fit.py)."""
