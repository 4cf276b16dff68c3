def Affine(*coefficients):
    return tuple(coefficients)
