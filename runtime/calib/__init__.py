"""A sensor's first calibration and its re-centring: the gel rim and disc in a rest image.
"""
