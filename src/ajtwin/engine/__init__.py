"""The glue: wires read → twin → detectors → store → publish for a finished print, a live
machine and a reprocessing task; computes nothing itself (no physics, no filtering)."""
