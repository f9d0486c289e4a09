//! From segmented instances to an instanced scene: per-Gaussian labels ([`labels`]), the stage's settings and verdicts
//! ([`options`]), the pose of each instance decided against the data ([`pose`]), templates and offsets ([`template`]),
//! the render check of every registered pose ([`verify`]), the group's poses
//! synchronised over a sparse pose graph ([`synchronise`]), background compaction
//! ([`compact`]) and the stage's time per step ([`timing`]).
pub mod build;
pub mod compact;
pub mod labels;
pub mod options;
pub mod pose;
pub mod pose_error;
pub mod synchronise;
pub mod template;
pub mod timing;
pub mod verify;
