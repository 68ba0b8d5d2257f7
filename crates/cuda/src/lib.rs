//! CUDA physics backends of Myriad: `cuda-naive` (every pair tested on the GPU, the
//! simplest GPU baseline) and `cuda` (device-resident state, LBVH broad phase), both bit for
//! bit identical to the CPU backends; [`create_backend`], which also resolves `auto`; and
//! [`DeviceReplicas`](replica::DeviceReplicas), every player's replica (protocol version
//! 3's choices) on a CUDA backend's device, which the factory hands out beside the
//! backend.
//!
//! Module map:
//! - [`compile`]: the embedded kernel sources, NVRTC compilation to a CUBIN and its cache;
//! - [`device`]: availability probe, context, stream, kernels, device and pinned memory;
//! - `launch`: typed device pointers and one argument struct per kernel;
//! - [`backend`]: [`CudaBackend`], the pipeline of both backends, one file per stage;
//! - [`replica`]: [`DeviceReplicas`](replica::DeviceReplicas), which shares the
//!   backend's device state, and the C it runs (`kernels/replica.cuh`) held to the host
//!   replica;
//! - [`params`]: the parameter block the kernels read.
//!
//! Without a CUDA driver, NVRTC or a device nothing here panics: the CUDA kinds return
//! [`PhysicsError::Unavailable`] with the reason, and `auto` falls back to `cpu`.

pub mod backend;
pub mod compile;
pub mod device;
pub(crate) mod launch;
pub mod params;
pub mod replica;

pub use backend::CudaBackend;

use myriad_physics::{Backend, BackendKind, PhysicsError};

/// What the factory makes: the physics backend, and what its device can do besides
/// physics.
pub struct CreatedBackend {
    /// The physics backend.
    pub backend: Box<dyn Backend>,
    /// Every player's replica on the backend's device (`Some` for the CUDA kinds).
    pub device_replicas: Option<replica::DeviceReplicas>,
}

impl std::fmt::Debug for CreatedBackend {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("CreatedBackend")
            .field("backend", &self.backend.description())
            .field("device_replicas", &self.device_replicas.is_some())
            .finish()
    }
}

/// A backend made elsewhere (a CPU kind, a zones gateway's): physics only.
impl From<Box<dyn Backend>> for CreatedBackend {
    fn from(backend: Box<dyn Backend>) -> CreatedBackend {
        CreatedBackend { backend, device_replicas: None }
    }
}

impl From<CudaBackend> for CreatedBackend {
    fn from(cuda: CudaBackend) -> CreatedBackend {
        let device_replicas = Some(cuda.device_replicas());
        CreatedBackend { backend: Box::new(cuda), device_replicas }
    }
}

/// Creates a backend of any kind: the CPU ones through `myriad_physics`, the CUDA ones
/// here, and `auto`: `cuda` when a driver, NVRTC and a device are present and the kernels
/// load, else `cpu`. The choice and its reason are logged. A CUDA backend comes with its
/// [`DeviceReplicas`](replica::DeviceReplicas).
pub fn create_backend(kind: BackendKind) -> Result<CreatedBackend, PhysicsError> {
    create_backend_on(kind, 0)
}

/// [`create_backend`] with the CUDA kinds on device `ordinal` (the CPU kinds ignore it).
pub fn create_backend_on(kind: BackendKind, ordinal: usize) -> Result<CreatedBackend, PhysicsError> {
    match kind {
        BackendKind::Cuda | BackendKind::CudaNaive => Ok(CudaBackend::on_device(kind, ordinal)?.into()),
        BackendKind::Auto => match CudaBackend::on_device(BackendKind::Cuda, ordinal) {
            Ok(b) => {
                tracing::info!("backend auto: using {}", b.description());
                Ok(b.into())
            }
            Err(e) => {
                tracing::info!("backend auto: using cpu, because {e}");
                Ok(myriad_physics::create_cpu_backend(BackendKind::Cpu)?.into())
            }
        },
        cpu => Ok(myriad_physics::create_cpu_backend(cpu)?.into()),
    }
}
