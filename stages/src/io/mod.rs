//! Real inputs and outputs: file sources and sinks, and the DAQ.
