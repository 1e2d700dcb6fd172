//! The data contract, on the [`crate::science`] core, in the order data flows: what arrives with each image
//! ([`acquisition`]) and where the synthetic world keeps it ([`world`]); the seeded draw streams every stage
//! takes its randomness from ([`rng`]); the terrain [`context`] cut around each crop and its
//! [`crater_frame`], framed by the catalogue or by draws of its simulated errors ([`catalogue_error`]); one DEM–image pair as a row
//! ([`schema`]); rows in Parquet [`shard`]s and on the server's [`wire`]; the [`manifest`] that lists and hashes them; the dataset card and
//! Croissant of a [`publication`]; and the epoch [`planner`] that reads a publication back in training order.

// What arrives with each image: the acquisition metadata JSON.
pub mod acquisition;

// Where the synthetic world keeps its files.
pub mod world;

// The seeded, purpose-keyed draw streams every stage takes its randomness from.
pub mod rng;

// The terrain context cut around each crop.
pub mod context;

// Where a crop lies in the frame of the nearest large catalogued crater.
pub mod crater_frame;

// A real catalogue's errors, simulated: the draws of the catalogue that frame a dataset's samples.
pub mod catalogue_error;

// One DEM–image pair as a Parquet row.
pub mod schema;

// Rows in Parquet shards: writing, reading, hashing.
pub mod shard;

// Rows on the wire: the Arrow IPC stream the dataset server sends.
pub mod wire;

// The manifest that lists and hashes the shards.
pub mod manifest;

// The dataset card and Croissant of a publication.
pub mod publication;

// The epoch planner that reads a publication back in training order.
pub mod planner;
