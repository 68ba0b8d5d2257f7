//! CUDA physics backends of Myriad: `cuda-naive` (every pair tested on the GPU, the
//! simplest GPU baseline) and `cuda` (device-resident state, LBVH broad phase), both bit for
//! bit identical to the CPU backends; and [`create_backend`], which also resolves `auto`.
//!
//! Module map:
//! - [`compile`]: the embedded kernel sources, NVRTC compilation to a CUBIN and its cache;
//! - [`device`]: availability probe, context, stream, kernels, device and pinned memory;
//! - `launch`: typed device pointers and one argument struct per kernel;
//! - [`backend`]: [`CudaBackend`], the pipeline of both backends, one file per stage;
//! - [`params`]: the parameter block the kernels read.
//!
//! Without a CUDA driver, NVRTC or a device nothing here panics: the CUDA kinds return
//! [`PhysicsError::Unavailable`] with the reason, and `auto` falls back to `cpu`.

pub mod backend;
pub mod compile;
pub mod device;
pub(crate) mod launch;
pub mod params;

pub use backend::CudaBackend;

use myriad_physics::{Backend, BackendKind, PhysicsError};

/// Creates a backend of any kind: the CPU ones through `myriad_physics`, the CUDA ones
/// here, and `auto`: `cuda` when a driver, NVRTC and a device are present and the kernels
/// load, else `cpu`. The choice and its reason are logged.
pub fn create_backend(kind: BackendKind) -> Result<Box<dyn Backend>, PhysicsError> {
    create_backend_on(kind, 0)
}

/// [`create_backend`] with the CUDA kinds on device `ordinal` (the CPU kinds ignore it).
pub fn create_backend_on(kind: BackendKind, ordinal: usize) -> Result<Box<dyn Backend>, PhysicsError> {
    match kind {
        BackendKind::Cuda | BackendKind::CudaNaive => Ok(Box::new(CudaBackend::on_device(kind, ordinal)?)),
        BackendKind::Auto => match CudaBackend::on_device(BackendKind::Cuda, ordinal) {
            Ok(b) => {
                tracing::info!("backend auto: using {}", b.description());
                Ok(Box::new(b))
            }
            Err(e) => {
                tracing::info!("backend auto: using cpu, because {e}");
                myriad_physics::create_cpu_backend(BackendKind::Cpu)
            }
        },
        cpu => myriad_physics::create_cpu_backend(cpu),
    }
}
