"""Figures (matplotlib, headless): deviation maps, histograms, zebra, the contour-curve plan."""
