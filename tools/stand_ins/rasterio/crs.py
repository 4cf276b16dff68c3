class CRS:
    def __init__(self, text):
        self.text = text

    @classmethod
    def from_user_input(cls, text):
        return cls(text)

    def to_wkt(self):
        return self.text
