//! gonio: plan, drive, rectify, store and compress gonioreflectometer acquisitions.
