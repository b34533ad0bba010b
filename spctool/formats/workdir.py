"""An SPC working directory: picture and landmark names -> files, by SPC's conventions.

spc-formats.md §0.1 and §7; cli-contract.md "Invocation".  ``SUMFILES/<PIC>.SUM``,
``NOMINALS/<PIC>.NOM``, photos as SPC finds them -- ``IMAGEFILES/<PIC>.DAT`` then
``IMAGEFILES1/`` … ``IMAGEFILES9/`` (FIND_PICFILE.f), then the INIT_LITHOS ``ALTDIR=`` folder
(LITHOS) -- and only AFTER that search fails, as a spctool extension, FITS/PGM/PNG (or a
lower-case ``.dat``) with the same stem in the same folders, ``MAPFILES/<LMK>.MAP``
(then ``EXTFILES/``), ``LMKFILES/<LMK>.LMK``, ``SHAPEFILES/SHAPE.TXT``,
``PICTLIST.TXT`` (``PICTLISTX.TXT`` preferred when present), ``LMRKLIST.TXT``,
``INIT_LITHOS.TXT``.  Explicit paths given by the user override every rule.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

from spctool.errors import SpcFormatError
from spctool.formats.guard import check_landmark_geometry, check_name, check_regular

PHOTO_SUFFIXES = (".DAT", ".dat", ".FITS", ".fits", ".FIT", ".fit", ".PGM", ".pgm", ".PNG", ".png")
#: spctool's extension, searched only after SPC's own search for ``<PIC>.DAT`` has failed
EXTRA_PHOTO_SUFFIXES = PHOTO_SUFFIXES[1:]
IMAGE_DIRS = ("IMAGEFILES",) + tuple(f"IMAGEFILES{k}" for k in range(1, 10))


def _missing(path: Path, what: str) -> SpcFormatError:
    return SpcFormatError(path, None, f"expected {what} (file not found)")


@dataclass
class WorkDir:
    """Resolve SPC names to paths below ``root`` (the ``-C DIR`` of the command line)."""

    root: Path = Path(".")
    _altdir: str | None = field(default=None, init=False, repr=False, compare=False)

    def __post_init__(self):
        self.root = Path(self.root)

    # -- paths ----------------------------------------------------------------------------------
    # every name becomes part of a path only through these methods, so they refuse a name that
    # could leave the working directory (guard.check_name: '/', '..', absolute paths, NUL)
    def sum_path(self, picture: str) -> Path:
        return self.root / "SUMFILES" / f"{check_name(picture, 'picture name')}.SUM"

    def nom_path(self, picture: str) -> Path:
        return self.root / "NOMINALS" / f"{check_name(picture, 'picture name')}.NOM"

    def map_path(self, landmark: str) -> Path:
        name = check_name(landmark, "landmark name")
        for folder in ("MAPFILES", "EXTFILES"):
            p = self.root / folder / f"{name}.MAP"
            if p.exists():
                return p
        return self.root / "MAPFILES" / f"{name}.MAP"

    def lmk_path(self, landmark: str) -> Path:
        return self.root / "LMKFILES" / f"{check_name(landmark, 'landmark name')}.LMK"

    def photo_folders(self) -> list[Path]:
        """IMAGEFILES/, IMAGEFILES1/ … IMAGEFILES9/ (FIND_PICFILE.f), then ``ALTDIR=`` (LITHOS)."""
        folders = [self.root / folder for folder in IMAGE_DIRS]
        if self._altdir is None:  # INIT_LITHOS is read once per WorkDir
            try:
                settings = self.read_settings()
                self._altdir = (settings.get_str("ALTDIR") or "") if settings is not None else ""
            except SpcFormatError:
                self._altdir = ""  # a broken INIT_LITHOS is reported by the command that needs it
        alt = self._altdir
        if alt.strip():
            folders.append(self.root / alt.strip())
        return folders

    def photo_path(self, picture: str) -> Path | None:
        """The photo of ``picture``, found as SPC finds it, else by spctool's extension (module docstring).

        SPC's search first: FIND_PICFILE.f INQUIREs ``./IMAGEFILES/<PIC>.DAT``, then ``IMAGEFILES1..9``,
        and LITHOS adds ``ALTDIR=`` -- so a stray PGM in IMAGEFILES/ never wins over the DAT in
        IMAGEFILES1/.  Only when no ``.DAT`` exists anywhere are other formats looked for, same order.
        """
        name = check_name(picture, "picture name")
        folders = self.photo_folders()
        for folder in folders:
            p = folder / f"{name}.DAT"
            if p.exists():
                return p
        for folder in folders:
            for suffix in EXTRA_PHOTO_SUFFIXES:
                p = folder / f"{name}{suffix}"
                if p.exists():
                    return p
        return None

    @property
    def shape_path(self) -> Path:
        return self.root / "SHAPEFILES" / "SHAPE.TXT"

    @property
    def settings_path(self) -> Path:
        return self.root / "INIT_LITHOS.TXT"

    @property
    def pictlist_path(self) -> Path:
        x = self.root / "PICTLISTX.TXT"
        return x if x.exists() else self.root / "PICTLIST.TXT"

    @property
    def lmrklist_path(self) -> Path:
        return self.root / "LMRKLIST.TXT"

    # -- readers ----------------------------------------------------------------------------------
    def read_picture(self, picture: str):
        """The SUM of ``picture``; ``picture`` may also be a path to a SUM file."""
        from spctool.formats.sumfile import read_sum

        p = Path(picture)
        if p.suffix.upper() == ".SUM" and p.exists():
            return read_sum(p)
        path = self.sum_path(picture)
        if not path.exists():
            raise _missing(path, f"the SUM file of picture {picture}")
        return read_sum(path)

    def read_settings(self, path=None):
        """INIT_LITHOS.TXT (or ``path``), or ``None`` when the working directory has none."""
        from spctool.formats.lithos import read_lithos

        p = Path(path) if path else self.settings_path
        if not p.exists():
            if path:
                raise _missing(p, "an INIT_LITHOS settings file")
            return None
        return read_lithos(p)

    def read_landmark(self, landmark: str):
        from spctool.formats.landmark import read_lmk

        p = Path(landmark)
        if p.suffix.upper() == ".LMK" and p.exists():
            return check_landmark_geometry(read_lmk(p), p)
        path = self.lmk_path(landmark)
        if not path.exists():
            raise _missing(path, f"the LMK file of landmark {landmark}")
        return check_landmark_geometry(read_lmk(path), path)  # what every stage needs of it

    def read_maplet(self, landmark: str):
        from spctool.formats.maplet import read_map

        p = Path(landmark)
        if p.suffix.upper() == ".MAP" and p.exists():
            check_regular(p, "a MAP file")
            m = check_landmark_geometry(read_map(p), p)
        else:
            path = self.map_path(landmark)
            if not path.exists():
                raise _missing(path, f"the MAP file of landmark {landmark}")
            check_regular(path, "a MAP file")  # a link to /dev/zero or a FIFO is refused, not read
            m = check_landmark_geometry(read_map(path), path)
        return m

    def read_photo(self, picture: str, npx: int | None = None, nln: int | None = None, **kw):
        from spctool.formats.photo import read_photo

        path = self.photo_path(picture)
        if path is None:
            raise _missing(
                self.root / "IMAGEFILES" / f"{picture.strip()}.DAT", f"the photo of picture {picture}"
            )
        return read_photo(path, npx=npx, nln=nln, **kw)

    def read_shape(self, path=None):
        """The global shape (ICQ, OBJ or VTK), or ``None`` when there is none."""
        from spctool.formats.mesh import read_shape

        p = Path(path) if path else self.shape_path
        if not p.exists():
            if path:
                raise _missing(p, "a shape model")
            return None
        return read_shape(p)

    # -- lists ----------------------------------------------------------------------------------
    def landmark_names(self) -> list[str]:
        """Candidate landmarks: LMRKLIST.TXT's active names, else every LMKFILES/*.LMK."""
        if self.lmrklist_path.exists():
            from spctool.formats.lists import read_lmrklist

            names = list(read_lmrklist(self.lmrklist_path).active_names)
            return [check_name(n, "landmark name", self.lmrklist_path) for n in names]
        folder = self.root / "LMKFILES"
        if folder.is_dir():
            return sorted(p.stem for p in folder.glob("*.LMK") if not p.stem.startswith("X"))
        return []

    def picture_names(self) -> list[str]:
        """Pictures in use from PICTLIST.TXT (PICTLISTX.TXT preferred), else every SUMFILES/*.SUM."""
        if self.pictlist_path.exists():
            from spctool.formats.lists import read_pictlist

            names = list(read_pictlist(self.pictlist_path).active_names)
            return [check_name(n, "picture name", self.pictlist_path) for n in names]
        folder = self.root / "SUMFILES"
        if folder.is_dir():
            return sorted(p.stem for p in folder.glob("*.SUM"))
        return []
