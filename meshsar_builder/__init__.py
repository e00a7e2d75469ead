"""meshsar-builder: the Cardiac Mesh-SAR dataset builder and reference SAR2Mesh trainer."""

__version__ = "0.1.0"
