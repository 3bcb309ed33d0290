/* Device layout of the kd-tree (kernels/kdtree_knn.cl, lib/src/kdtree/kdtree.cpp).
 * Valid OpenCL C and valid C++: the host checks it with static_assert (lib/src/kdtree/kdtree.cpp).
 *
 * Nodes are stored depth-first: an inner node's left child is the next node (index + 1), its right
 * child is `right`. A leaf holds `count` points starting at `begin` in the reordered point array,
 * where each point is a float4 whose w lane carries the caller's original index (int bits). */
#ifndef BHCL_KDTREE_LAYOUT_H
#define BHCL_KDTREE_LAYOUT_H

#include "bhcl_shared.h"

/* dim of a leaf; 0, 1, 2 are the split dimensions x, y, z of an inner node. */
#define BHCL_KD_LEAF 3u

/* 16 bytes. Inner node: points of the left subtree have coordinate[dim] <= split, points of the
 * right subtree >= split (duplicates of the split value may sit on both sides). */
typedef struct bhcl_kd_node {
  bhcl_f32 split;  /* inner: the split value; leaf: unused (0) */
  bhcl_u32 dim;    /* 0..2 inner, BHCL_KD_LEAF for a leaf */
  bhcl_u32 a;      /* inner: index of the right child; leaf: first point */
  bhcl_u32 b;      /* inner: unused (0); leaf: number of points */
} bhcl_kd_node;

/* A reordered point: position and the caller's index. Same size as float4. */
typedef struct bhcl_kd_point {
  bhcl_f32 x, y, z;
  bhcl_i32 id;
} bhcl_kd_point;

#endif /* BHCL_KDTREE_LAYOUT_H */
