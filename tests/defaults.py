"""The shipped settings, and the analysis tolerances derived from them, for tests that call stages directly."""
from bonecad.analysis.model import continuity_tolerances, tessellation_settings
from bonecad.analysis.statistics import settings_band_edges
from bonecad.settings import Settings

SETTINGS = Settings.load()
#: tessellation tolerances and seam-class thresholds of [analysis]
TESSELLATION = tessellation_settings(SETTINGS.analysis)
CONTINUITY = continuity_tolerances(SETTINGS.analysis)
#: histogram band edges of [analysis] (mm)
BANDS_MM = settings_band_edges(SETTINGS.analysis)
