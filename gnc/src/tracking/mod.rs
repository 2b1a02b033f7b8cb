//! Vision algorithms of seed 000, 8.1 and 8.4, free of the framework's module machinery: fiducial
//! markers and the poses they give ([`markers`]), the operator-selected target's image tracker
//! ([`template`]) and its position by stereo ([`locate`]).

pub mod locate;
pub mod markers;
pub mod template;
