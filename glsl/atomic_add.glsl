// Float accumulation into storage buffers. Kernels that include this file are compiled twice by
// build.rs: as NAME with float atomics (GL_EXT_shader_atomic_float) and as NAME_cas with
// NO_FLOAT_ATOMICS defined, where a compare-and-swap loop on the bit pattern does the add (for
// devices without shaderBufferFloat32AtomicAdd). Accumulator buffers are declared with GRAD_T.
#ifndef INSTGS_ATOMIC_ADD_GLSL
#define INSTGS_ATOMIC_ADD_GLSL
#ifdef NO_FLOAT_ATOMICS
#define GRAD_T uint
#define ATOMIC_ADD_F(arr, index, value)                                                          \
    {                                                                                            \
        uint atomic_i_ = (index);                                                                \
        float atomic_v_ = (value);                                                               \
        uint atomic_old_ = arr[atomic_i_];                                                       \
        for (;;) {                                                                               \
            uint atomic_new_ = floatBitsToUint(uintBitsToFloat(atomic_old_) + atomic_v_);        \
            uint atomic_prev_ = atomicCompSwap(arr[atomic_i_], atomic_old_, atomic_new_);        \
            if (atomic_prev_ == atomic_old_) break;                                              \
            atomic_old_ = atomic_prev_;                                                          \
        }                                                                                        \
    }
#else
#extension GL_EXT_shader_atomic_float : require
#define GRAD_T float
#define ATOMIC_ADD_F(arr, index, value) atomicAdd(arr[index], value)
#endif
#endif
