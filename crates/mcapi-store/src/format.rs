//! The version of the store's file format, which the database records and
//! the opening checks (db.rs upgrades older versions; error.rs names it
//! when a file is newer than this build).

/// Version of the on-disk layout. Formats 2 and 3 are upgraded at open;
/// a file of any other version is refused.
pub const FORMAT_VERSION: u64 = 4;
