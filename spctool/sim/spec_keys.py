"""The SPEC.toml key table of ``spctool simulate``: one table drives validation, defaults, the
documentation and ``--help`` (:mod:`spctool.sim.simulate` reads SPECs with it).

Plain data and text only — no numerics — so the command line can show the reference without loading
the simulator.
"""

from __future__ import annotations

import json

__all__ = ["DEFAULT_PICTURES", "PHOTO_SUFFIX", "PICTURE_KEYS", "SPEC_KEYS", "spec_help"]


#: (section, key, default, kind, help).  Section "" is the top level; "pictures" entries are in
#: :data:`PICTURE_KEYS`.
SPEC_KEYS: tuple[tuple[str, str, object, str, str], ...] = (
    ("", "seed", 1, "int", "the one seed of every random draw (terrain, placement, perturbations, noise)"),
    ("body", "name", "SYNTH", "str", "INIT_LITHOS BODY= name"),
    ("body", "radii_km", [0.28, 0.24, 0.20], "vec3", "ellipsoid semi-axes along x, y, z (km)"),
    (
        "body",
        "shape",
        "",
        "str",
        "reference shape file (ICQ/OBJ/VTK, relative to the SPEC) used instead of the ellipsoid",
    ),
    ("body", "q", 64, "int", "ICQ resolution Q of SHAPEFILES/SHAPE.TXT (power of 2)"),
    (
        "terrain",
        "split_cells",
        4.0,
        "float",
        "features/wavelengths >= split_cells x shape cell go into the global shape, smaller ones only into "
        "the truth patches",
    ),
    (
        "terrain.craters",
        "coefficient",
        0.05,
        "float",
        "N(>D) per km2 = coefficient*(D/1 km)^-slope; 0 = none",
    ),
    ("terrain.craters", "slope", 2.0, "float", "power-law slope of the cumulative crater count"),
    ("terrain.craters", "min_diameter_km", 0.001, "float", "smallest crater diameter"),
    ("terrain.craters", "max_diameter_km", 0.12, "float", "largest crater diameter"),
    ("terrain.craters", "depth_ratio", 0.2, "float", "bowl depth / diameter"),
    ("terrain.craters", "rim_ratio", 0.04, "float", "rim height / diameter"),
    ("terrain.craters", "albedo", 0.06, "float", "largest albedo brightening of a fresh crater floor"),
    (
        "terrain.boulders",
        "coefficient",
        0.001,
        "float",
        "N(>D) per km2 = coefficient*(D/1 km)^-slope; 0 = none",
    ),
    ("terrain.boulders", "slope", 2.5, "float", "power-law slope of the cumulative boulder count"),
    ("terrain.boulders", "min_diameter_km", 0.0004, "float", "smallest boulder diameter"),
    ("terrain.boulders", "max_diameter_km", 0.005, "float", "largest boulder diameter"),
    ("terrain.boulders", "height_ratio", 0.5, "float", "boulder height / diameter"),
    (
        "terrain.boulders",
        "albedo_spread",
        0.15,
        "float",
        "boulder albedo offsets are uniform in +-albedo_spread",
    ),
    ("terrain.roughness", "amplitude_km", 0.0003, "float", "fBm height amplitude of the longest wavelength"),
    ("terrain.roughness", "hurst", 0.8, "float", "Hurst exponent (amplitude ~ wavelength^hurst)"),
    ("terrain.roughness", "min_wavelength_km", 0.0003, "float", "shortest roughness wavelength"),
    ("terrain.roughness", "max_wavelength_km", 0.03, "float", "longest roughness wavelength"),
    ("terrain.albedo", "contrast", 0.08, "float", "albedo = 1 + contrast*fBm (+ crater/boulder terms)"),
    ("terrain.albedo", "hurst", 0.5, "float", "Hurst exponent of the albedo field"),
    ("terrain.albedo", "min_wavelength_km", 0.001, "float", "shortest albedo wavelength"),
    ("terrain.albedo", "max_wavelength_km", 0.1, "float", "longest albedo wavelength"),
    ("terrain.albedo", "min", 0.05, "float", "albedo floor"),
    ("terrain.albedo", "max", 1.95, "float", "albedo ceiling (MAP bytes hold 0.01 ... 1.99)"),
    ("maplets", "count", 12, "int", "number of landmarks (when names/positions do not fix it)"),
    ("maplets", "names", [], "strs", "landmark names (6 characters); default prefix + number"),
    ("maplets", "prefix", "SM", "str", "prefix of generated landmark names"),
    ("maplets", "positions", [], "latlons", "[[lat_deg, lon_deg], ...] planetocentric; default: automatic"),
    ("maplets", "scale_km", 0.0005, "float", "maplet SCALE (km per cell)"),
    ("maplets", "qsz", 24, "int", "maplet QSZ: (2*qsz+1)^2 cells"),
    (
        "maplets",
        "truth_factor",
        3,
        "int",
        "truth cells per maplet cell (Shoemaker et al. 2016: 3 mm truth under 1 cm maplets)",
    ),
    ("maplets", "margin", 12, "int", "truth patch extends this many maplet cells beyond the maplet"),
    (
        "maplets",
        "smoothing_cells",
        0.5,
        "float",
        "Gaussian sigma (maplet cells) of the truth -> maplet smoothing",
    ),
    (
        "maplets",
        "min_separation_km",
        0.0,
        "float",
        "automatic placement: minimum distance (0 = truth patch side)",
    ),
    ("maplets", "max_emission_deg", 50.0, "float", "automatic placement: emission limit in every picture"),
    ("maplets", "max_incidence_deg", 65.0, "float", "automatic placement: incidence limit in every picture"),
    (
        "maplets",
        "edge_margin_px",
        8.0,
        "float",
        "automatic placement: keep maplets this far inside the photos",
    ),
    (
        "maplets",
        "landmark_sigma_km",
        0.0,
        "float",
        "a-priori landmark error added to the written VLM and MAP V",
    ),
    ("maplets", "write_truth", False, "bool", "also write the truth patches as TRUTHFILES/<NAME>.MAP"),
    ("maplets", "mapvers", 0, "int", "MAP version byte (INIT_LITHOS MAPVERS=)"),
    ("camera", "npx", 768, "int", "photo width (samples)"),
    ("camera", "nln", 768, "int", "photo height (lines)"),
    ("camera", "mmfl", 7.68, "float", "focal length (mm; Shoemaker et al. 2016, Table 1)"),
    (
        "camera",
        "ctr",
        [],
        "floats",
        "principal point (sample, line); default the detector centre ((NPX+1)/2, (NLN+1)/2)",
    ),
    (
        "camera",
        "kmatrix",
        [[454.54, 0.0, 0.0], [0.0, -454.54, 0.0]],
        "kmatrix",
        "2x3 K-matrix in px/mm (Shoemaker et al. 2016: Kx = 454.54, Ky = -454.54; third column "
        "multiplies x*y)",
    ),
    ("camera", "distortion", "OWEN", "str", "INIT_LITHOS DISTORT= model (OWEN, RADIAL, ... or NONE)"),
    (
        "camera",
        "coefficients",
        [0.0, 1e-4, 2e-3, 1e-5, 0.0, 1e-5, 1e-5],
        "floats",
        "distortion coefficients P0 ... PJ in SPC order",
    ),
    ("camera", "template", "", "str", "DISTORT= picture-name template; default '#' for every character"),
    ("detector", "bits", 16, "int", "DN bits (8 or 16) unless a picture overrides it"),
    ("detector", "exposure", "auto", "exposure", "DN of radiance 1, or 'auto'"),
    (
        "detector",
        "auto_level",
        0.8,
        "float",
        "'auto': the 99.5th radiance percentile maps to this fraction of full scale",
    ),
    ("detector", "full_well_electrons", 40000.0, "float", "electrons at full scale (sets electrons per DN)"),
    ("detector", "read_noise_electrons", 20.0, "float", "Gaussian read noise (electrons); 0 = none"),
    ("detector", "shot_noise", True, "bool", "add Gaussian shot noise (variance = signal electrons)"),
    ("detector", "supersample", 2, "int", "n x n rays per pixel"),
    ("detector", "photometry", "spc", "str", "spc, mcewen, fixed or lambert (illumination law)"),
    ("detector", "shadows", True, "bool", "trace cast shadows"),
    (
        "perturbation",
        "position_sigma_km",
        0.001,
        "float",
        "a-priori spacecraft position error, per component",
    ),
    ("perturbation", "attitude_sigma_deg", 0.02, "float", "a-priori pointing error, per camera axis"),
    ("perturbation", "sun_sigma_deg", 0.0, "float", "a-priori Sun direction error, per axis"),
)

#: keys of each ``[[pictures]]`` entry: (key, default, kind, help); None defaults are derived.
PICTURE_KEYS: tuple[tuple[str, object, str, str], ...] = (
    ("name", "", "str", "12-character picture name; default P000000001A1, P000000002A1, ..."),
    ("aim_lat_deg", 0.0, "float", "latitude of the surface point at the photo centre"),
    ("aim_lon_deg", 0.0, "float", "longitude of the surface point at the photo centre"),
    ("view_lat_deg", None, "float", "direction of the camera seen from the aim point (default: the aim's)"),
    ("view_lon_deg", None, "float", "longitude of that direction (default: the aim's)"),
    ("range_km", 1.8, "float", "distance camera - aim point"),
    ("roll_deg", 0.0, "float", "rotation of the camera about its boresight"),
    ("sun_lat_deg", 20.0, "float", "latitude of the Sun direction (body frame)"),
    ("sun_lon_deg", -30.0, "float", "longitude of the Sun direction"),
    ("utc", "", "str", "SUM time tag; default 2024 JAN 01 00:00:00.000 + 10 min per picture"),
    ("format", "dat", "str", "photo format: dat, fits, pgm or png"),
    ("bits", 0, "int", "DN bits of this photo (0 = detector.bits)"),
)

#: the pictures of the default world: one near nadir and three oblique views of the same region
DEFAULT_PICTURES = (
    {"aim_lat_deg": 10.0, "aim_lon_deg": 20.0, "sun_lat_deg": 30.0, "sun_lon_deg": -15.0, "format": "dat"},
    {
        "aim_lat_deg": 10.0,
        "aim_lon_deg": 20.0,
        "view_lat_deg": 25.0,
        "view_lon_deg": 40.0,
        "range_km": 2.0,
        "sun_lat_deg": 35.0,
        "sun_lon_deg": 55.0,
        "roll_deg": 10.0,
        "format": "dat",
    },
    {
        "aim_lat_deg": 10.0,
        "aim_lon_deg": 20.0,
        "view_lat_deg": -5.0,
        "view_lon_deg": 8.0,
        "range_km": 1.9,
        "sun_lat_deg": 0.0,
        "sun_lon_deg": -25.0,
        "roll_deg": -15.0,
        "format": "fits",
    },
    {
        "aim_lat_deg": 10.0,
        "aim_lon_deg": 20.0,
        "view_lat_deg": 20.0,
        "view_lon_deg": 15.0,
        "range_km": 1.7,
        "sun_lat_deg": 50.0,
        "sun_lon_deg": 35.0,
        "format": "pgm",
        "bits": 8,
    },
)

PHOTO_SUFFIX = {"dat": ".DAT", "fits": ".FITS", "pgm": ".PGM", "png": ".PNG"}


def _wrap(text: str, width: int, indent: int) -> list[str]:
    import textwrap

    return textwrap.wrap(text, width=width, initial_indent="", subsequent_indent=" " * indent) or [""]


def spec_help(width: int = 100) -> str:
    """The SPEC key reference (the same text as the module docstring's table)."""
    lines: list[str] = []
    current = None
    for section, key, default, _kind, text in SPEC_KEYS:
        if section != current:
            current = section
            lines.append(f"[{section}]" if section else "(top level)")
        shown = json.dumps(default)
        head = f"  {key} = {shown}: "
        body = _wrap(head + text, width, 6)
        lines.extend(body)
    lines.append("[[pictures]] (repeat for each picture; default: 4 views of one region)")
    for key, default, _kind, text in PICTURE_KEYS:
        shown = "derived" if default is None else json.dumps(default)
        lines.extend(_wrap(f"  {key} = {shown}: {text}", width, 6))
    return "\n".join(lines)
