//! modulator
