//! Subcommands that are thin layers over the library.

pub mod check;
pub mod schema;
