//! Pure models: parameters in, profile or kernel out (docs/design.md §3 step 3).
//! No I/O beyond (de)serialisation.

pub mod basis;
pub mod burley;
pub mod kernel;
pub mod meta;
