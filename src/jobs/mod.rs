//! Jobs: everything that touches files, sits above the pure library
//! ([`crate::forward`], [`crate::fit`], [`crate::metamodel`],
//! [`crate::render`]) and below the command line.
//!
//! * [`store`] reads and writes documents (atomic writes, format-tag checks);
//!   [`shipped`] holds the models and scenes built into the binary and finds
//!   overrides; [`scene`] reads scene files and their textures;
//! * [`render`] (`svkernel render`), [`compare`] (error against time),
//!   [`experiments`], [`extend`] (the missing kernel range, fitted in
//!   memory and cached), [`demo`];
//! * [`fit_profiles`] and [`fit_kernels`] (the fit commands: the pure fits
//!   of [`crate::fit`] plus their reports and plots);
//! * [`output`] (EXR, PNG, npy), [`plot`], [`report`] (HTML + Markdown); progress
//!   of long steps is [`crate::progress`].

pub mod compare;
pub mod demo;
pub mod design;
pub mod experiments;
pub mod extend;
pub mod fit_kernels;
pub mod fit_profiles;
pub mod medium;
pub mod output;
pub mod plot;
pub mod render;
pub mod report;
pub mod scene;
pub mod shipped;
pub mod store;
