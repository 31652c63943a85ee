/*------------------------------------------------------------------------------
   Test harness around the OCamCalib C functions get_ocam_model, cam2world and
   world2cam, which are reproduced VERBATIM below from the C example code of
   Davide Scaramuzza's OCamCalib toolbox (ocam_functions.cpp / ocam_functions.h):

      Example code that shows the use of the 'cam2world" and 'world2cam" functions
      Shows also how to undistort images into perspective or panoramic images
      Copyright (C) 2008 DAVIDE SCARAMUZZA, ETH Zurich
      Author: Davide Scaramuzza - email: davide.scaramuzza@ieee.org

   Copied from github.com/mhirano/OCamCalib_undistortFunctions
   (ocam_functions.cpp, ocam_functions.h; commit
   1afdcd1d8ff85f4868945b97e75c895912ba0007); identical in
   github.com/evroon/undistort-functions (commit 13041c3a...).  Only the
   OpenCV include and the LUT functions were left out.  main() is ours.

   Usage:  cc -O2 -o ocam_harness ocam_harness.c -lm
           ./ocam_harness calib_results.txt < queries
   Query lines (one result line each, numbers printed with %.17g):
      w X Y Z   -> world2cam: "row col"
      c row col -> cam2world: "x y z"
      m         -> the parsed model: "length_pol pol..." / "length_invpol
                   invpol..." / "xc yc" / "c d e" / "height width" (5 lines)
------------------------------------------------------------------------------*/

#include <stdlib.h>
#include <stdio.h>
#include <string.h>
#include <float.h>
#include <math.h>

#define CMV_MAX_BUF 1024
#define MAX_POL_LENGTH 64

struct ocam_model
{
  double pol[MAX_POL_LENGTH];    // the polynomial coefficients: pol[0] + x"pol[1] + x^2*pol[2] + ... + x^(N-1)*pol[N-1]
  int length_pol;                // length of polynomial
  double invpol[MAX_POL_LENGTH]; // the coefficients of the inverse polynomial
  int length_invpol;             // length of inverse polynomial
  double xc;         // row coordinate of the center
  double yc;         // column coordinate of the center
  double c;          // affine parameter
  double d;          // affine parameter
  double e;          // affine parameter
  int width;         // image width
  int height;        // image height
};

/* ---- verbatim from ocam_functions.cpp ---------------------------------- */

//------------------------------------------------------------------------------
int get_ocam_model(struct ocam_model *myocam_model, char *filename)
{
 double *pol        = myocam_model->pol;
 double *invpol     = myocam_model->invpol; 
 double *xc         = &(myocam_model->xc);
 double *yc         = &(myocam_model->yc); 
 double *c          = &(myocam_model->c);
 double *d          = &(myocam_model->d);
 double *e          = &(myocam_model->e);
 int    *width      = &(myocam_model->width);
 int    *height     = &(myocam_model->height);
 int *length_pol    = &(myocam_model->length_pol);
 int *length_invpol = &(myocam_model->length_invpol);
 FILE *f;
 char buf[CMV_MAX_BUF];
 int i;
 
 //Open file
 if(!(f=fopen(filename,"r")))
 {
   printf("File %s cannot be opened\n", filename);				  
   return -1;
 }
 
 //Read polynomial coefficients
 fgets(buf,CMV_MAX_BUF,f);
 fscanf(f,"\n");
 fscanf(f,"%d", length_pol);
 for (i = 0; i < *length_pol; i++)
 {
     fscanf(f," %lf",&pol[i]);
 }

 //Read inverse polynomial coefficients
 fscanf(f,"\n");
 fgets(buf,CMV_MAX_BUF,f);
 fscanf(f,"\n");
 fscanf(f,"%d", length_invpol);
 for (i = 0; i < *length_invpol; i++)
 {
     fscanf(f," %lf",&invpol[i]);
 }
 
 //Read center coordinates
 fscanf(f,"\n");
 fgets(buf,CMV_MAX_BUF,f);
 fscanf(f,"\n");
 fscanf(f,"%lf %lf\n", xc, yc);

 //Read affine coefficients
 fgets(buf,CMV_MAX_BUF,f);
 fscanf(f,"\n");
 fscanf(f,"%lf %lf %lf\n", c,d,e);

 //Read image size
 fgets(buf,CMV_MAX_BUF,f);
 fscanf(f,"\n");
 fscanf(f,"%d %d", height, width);

 fclose(f);
 return 0;
}

//------------------------------------------------------------------------------
void cam2world(double point3D[3], double point2D[2], struct ocam_model *myocam_model)
{
 double *pol    = myocam_model->pol;
 double xc      = (myocam_model->xc);
 double yc      = (myocam_model->yc); 
 double c       = (myocam_model->c);
 double d       = (myocam_model->d);
 double e       = (myocam_model->e);
 int length_pol = (myocam_model->length_pol); 
 double invdet  = 1/(c-d*e); // 1/det(A), where A = [c,d;e,1] as in the Matlab file

 double xp = invdet*(    (point2D[0] - xc) - d*(point2D[1] - yc) );
 double yp = invdet*( -e*(point2D[0] - xc) + c*(point2D[1] - yc) );
  
 double r   = sqrt(  xp*xp + yp*yp ); //distance [pixels] of  the point from the image center
 double zp  = pol[0];
 double r_i = 1;
 int i;
 
 for (i = 1; i < length_pol; i++)
 {
   r_i *= r;
   zp  += r_i*pol[i];
 }
 
 //normalize to unit norm
 double invnorm = 1/sqrt( xp*xp + yp*yp + zp*zp );
 
 point3D[0] = invnorm*xp;
 point3D[1] = invnorm*yp; 
 point3D[2] = invnorm*zp;
}

//------------------------------------------------------------------------------
void world2cam(double point2D[2], double point3D[3], struct ocam_model *myocam_model)
{
 double *invpol     = myocam_model->invpol; 
 double xc          = (myocam_model->xc);
 double yc          = (myocam_model->yc); 
 double c           = (myocam_model->c);
 double d           = (myocam_model->d);
 double e           = (myocam_model->e);
 int    width       = (myocam_model->width);
 int    height      = (myocam_model->height);
 int length_invpol  = (myocam_model->length_invpol);
 double norm        = sqrt(point3D[0]*point3D[0] + point3D[1]*point3D[1]);
 double theta       = atan(point3D[2]/norm);
 double t, t_i;
 double rho, x, y;
 double invnorm;
 int i;
  
  if (norm != 0) 
  {
    invnorm = 1/norm;
    t  = theta;
    rho = invpol[0];
    t_i = 1;

    for (i = 1; i < length_invpol; i++)
    {
      t_i *= t;
      rho += t_i*invpol[i];
    }

    x = point3D[0]*invnorm*rho;
    y = point3D[1]*invnorm*rho;
  
    point2D[0] = x*c + y*d + xc;
    point2D[1] = x*e + y   + yc;
  }
  else
  {
    point2D[0] = xc;
    point2D[1] = yc;
  }
}

/* ---- end of verbatim part ---------------------------------------------- */

int main(int argc, char **argv)
{
  struct ocam_model model;
  char line[4096];
  int i;

  if (argc < 2) {
    fprintf(stderr, "usage: %s calib_results.txt < queries\n", argv[0]);
    return 2;
  }
  memset(&model, 0, sizeof model);
  if (get_ocam_model(&model, argv[1]) != 0) return 1;

  while (fgets(line, sizeof line, stdin)) {
    char kind;
    double a, b, c;
    if (sscanf(line, " %c", &kind) != 1) continue;  /* blank line */
    if (kind == 'w') {
      double p3[3], p2[2];
      if (sscanf(line, " %*c %lf %lf %lf", &a, &b, &c) != 3) goto bad;
      p3[0] = a; p3[1] = b; p3[2] = c;
      world2cam(p2, p3, &model);
      printf("%.17g %.17g\n", p2[0], p2[1]);
    } else if (kind == 'c') {
      double p2[2], p3[3];
      if (sscanf(line, " %*c %lf %lf", &a, &b) != 2) goto bad;
      p2[0] = a; p2[1] = b;
      cam2world(p3, p2, &model);
      printf("%.17g %.17g %.17g\n", p3[0], p3[1], p3[2]);
    } else if (kind == 'm') {
      printf("%d", model.length_pol);
      for (i = 0; i < model.length_pol && i < MAX_POL_LENGTH; i++) printf(" %.17g", model.pol[i]);
      printf("\n%d", model.length_invpol);
      for (i = 0; i < model.length_invpol && i < MAX_POL_LENGTH; i++) printf(" %.17g", model.invpol[i]);
      printf("\n%.17g %.17g\n%.17g %.17g %.17g\n%d %d\n", model.xc, model.yc,
             model.c, model.d, model.e, model.height, model.width);
    } else {
      goto bad;
    }
    continue;
  bad:
    fprintf(stderr, "bad query line: %s", line);
    return 3;
  }
  return 0;
}
