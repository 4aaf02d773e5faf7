"""A toy plant that reads a file (as an FMU plant reads its .fmu): its `source_files()` names it,
so a design file records the file's SHA-256 (`sep_estimator.design_source`)."""
from pathlib import Path

from broken_plants import ToyPlant


class FileToy(ToyPlant):
    """ToyPlant whose decay rate is read from a text file `table`."""

    def __init__(self, table: str, n_x: int = 6):
        self.table = str(table)
        super().__init__(n_x=n_x, decay=float(Path(self.table).read_text().split()[0]))

    def config(self) -> dict:
        return {"table": self.table, "n_x": self.n_x}

    def source_files(self) -> dict:
        return {"table.txt": self.table}

