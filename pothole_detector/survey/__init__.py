"""Recorded drives into road surveys: the ego-motion and GNSS (``motion``), pothole ids that stay
with a physical pothole (``tracking``), the fused road elevation map (``roadmap``), the survey of
bags (``drive``), Ray fleets (``fleet``), report.html (``report``) and the GIS files (``gis``).
It calls the method and the recordings layer; nothing below it calls back."""
