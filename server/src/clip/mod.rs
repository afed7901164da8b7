//! Animation clips and sampling.
