//! Forest analysis: the ground model, stems and their diameters at breast height.
//!
//! Built on the geometry room (`geom`) and used by the `segment` and `dbh` stages and by
//! `sylva inventory`; nothing here knows about jobs or HTTP.

pub mod ground;
