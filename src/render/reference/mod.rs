//! CPU reference twins of the kernels: [`forward`] (f32, pass by pass as the GPU) and
//! [`backward`] (f64 projection, compositing, loss and Adam with their vector-Jacobian
//! products, themselves checked against finite differences).
pub mod backward;
pub mod forward;
