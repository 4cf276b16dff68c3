class CRSError(ValueError):
    pass


class RasterioIOError(OSError):
    pass
