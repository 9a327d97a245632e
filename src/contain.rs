//! Per-frame fault containment: a panic while one frame is worked on (in a source, prepare, the
//! encoder or the tracker) becomes an error naming the stage, so the stage goes on with the next
//! frame and the frame is a counted rejection. A leaf, so that sources and the pipeline's stages
//! share it without depending on each other.

/// The message of a caught panic.
fn panic_message(payload: &(dyn std::any::Any + Send)) -> String {
    payload
        .downcast_ref::<&str>()
        .map(|s| s.to_string())
        .or_else(|| payload.downcast_ref::<String>().cloned())
        .unwrap_or_else(|| "unknown panic".into())
}

/// Runs one frame's work; a panic in it becomes an error naming the stage (the stage goes on
/// with the next frame, and the frame is a counted rejection).
pub(crate) fn contained<T>(stage: &str, work: impl FnOnce() -> T) -> Result<T, String> {
    std::panic::catch_unwind(std::panic::AssertUnwindSafe(work)).map_err(|payload| {
        let message = format!("internal error in {stage}: {}", panic_message(payload.as_ref()));
        log::error!("{message}");
        message
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_panic_in_a_frame_is_an_error_naming_the_stage() {
        assert_eq!(contained("prepare", || 7), Ok(7));
        let error = contained("prepare", || -> u32 { panic!("index out of bounds") }).unwrap_err();
        assert_eq!(error, "internal error in prepare: index out of bounds");
        let error = contained("encode", || -> u32 { panic!("{} points", 3) }).unwrap_err();
        assert_eq!(error, "internal error in encode: 3 points");
    }
}
