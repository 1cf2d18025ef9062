/* The arm library (rscasadi codegen): CasADi's declarations of its Functions, the arm's size and
   its model file's numbers, and the structured kernels' declarations.  Generated for ${model}. */
#ifndef ${GUARD}
#define ${GUARD}

#include "${casadi_header}"
${macros}
#ifdef __cplusplus
extern "C" {
#endif
${declarations}
#ifdef __cplusplus
}
#endif

#endif
