// The fused attention loop for AVX-512 (F, BW, VL, DQ) + FMA (see
// attention_rows_impl.h). Compiled with those -m flags; called only where the
// CPU has them.
#define CPU_CAPABILITY AVX512
#define CPU_CAPABILITY_AVX512
#define FD_ATTENTION_ROWS_FN AttendHeadsAvx512
#include "model/runtime/attention_rows_impl.h"
