"""Data path: BEAP resampling, datamanager, dataparsers and the embedded demo scene."""
