//! Spiking encoders: analog taxel signals to spike events (SPEC.md section 2).
